"""``onfly sim-vehicle``: a simulated PX4 or ArduCopter vehicle served over MAVLink.

Run it in one terminal and point a companion (``onfly fly --connect ...``, MAVSDK, MAVROS, QGC)
at it. Like PX4 SITL, the default URL sends to the companion's port on localhost
(``udpout:127.0.0.1:14540``); the companion listens there (``udpin:127.0.0.1:14540``).

The embedded world's camera (``--scene`` / ``--camera``) is not wired in yet: the world package
was not part of the code base when this command was written. The vehicle flies without a camera.
"""

from __future__ import annotations

import argparse
import time

from onfly.cli import CliError
from onfly.mavlink.link import LinkError, MavlinkLink
from onfly.mavlink.sim_vehicle import SimMavlinkVehicle, SimVehicleConfig

NAME = "sim-vehicle"
HELP = "serve a simulated PX4/ArduPilot vehicle over MAVLink (for companion tests without hardware)"
DESCRIPTION = __doc__


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mavlink", default="udpout:127.0.0.1:14540", metavar="URL",
                        help="vehicle link: udpout:HOST:PORT (default, like PX4 SITL), udpin:, tcpin:, tcp:")
    parser.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4", help="which autopilot's rules to follow")
    parser.add_argument("--system-id", type=int, default=1, help="MAVLink system id of the vehicle (default 1)")
    parser.add_argument("--telemetry-rate-hz", type=float, default=50.0, help="LOCAL_POSITION_NED and attitude rate")
    parser.add_argument("--duration-s", type=float, default=None, help="stop after this many seconds (default: until Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    try:
        config = SimVehicleConfig(autopilot=args.autopilot, system_id=args.system_id, telemetry_rate_hz=args.telemetry_rate_hz)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    if args.duration_s is not None and not args.duration_s > 0:
        raise CliError(f"--duration-s must be positive, got {args.duration_s}")
    try:
        link = MavlinkLink(args.mavlink, config.system_id, config.component_id)
        link.connect()
    except LinkError as exc:
        raise CliError(str(exc)) from exc
    vehicle = SimMavlinkVehicle(link, config)
    print(f"onfly sim-vehicle: {args.autopilot} vehicle (system {config.system_id}) on {args.mavlink}; no camera (embedded world not wired in)")
    t0 = time.monotonic()
    last_mode = None
    with vehicle:
        try:
            while args.duration_s is None or time.monotonic() - t0 < args.duration_s:
                mode = (vehicle.mode_name, vehicle.armed)
                if mode != last_mode:
                    p = vehicle.position_enu()
                    print(f"t={time.monotonic() - t0:7.2f} s  mode {mode[0]:<14} armed={mode[1]!s:<5} p_enu=({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) m")
                    last_mode = mode
                time.sleep(0.1)
        except KeyboardInterrupt:
            print("onfly sim-vehicle: stopped")
    return 0
