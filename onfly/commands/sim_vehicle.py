"""``onfly sim-vehicle``: a simulated PX4 or ArduCopter vehicle served over MAVLink.

Run it in one terminal and point a companion (``onfly fly --connect ...``, MAVSDK, MAVROS, QGC)
at it. Like PX4 SITL, the default URL sends to the companion's port on localhost
(``udpout:127.0.0.1:14540``); the companion listens there (``udpin:127.0.0.1:14540``).

Without ``--scene`` / ``--task`` the vehicle is a point mass without a camera (fast; for link
and rule tests). With them it flies in the embedded world: the world's vehicle dynamics
(benchmark limits), exact collisions against the scene (a collision disarms it) and, with
``--camera tcp://127.0.0.1:PORT``, its camera served to the companion at ``--camera-rate-hz``
(default 2 Hz at 320 x 214, 90 x 60 deg, as the benchmark). It starts on the ground below the
scene's (or the task's) start pose; the companion takes off.

The vehicle follows PX4's or ArduCopter's rules (docs/flight.md lists them with their sources).
LOCAL_POSITION_NED is relative to the estimator's origin (where the vehicle boots, turned by
--estimator-yaw-deg), not the scene's origin, and camera frames are posed in that frame too, as
a camera stamped by the vehicle's estimator is. --profile indoor (default): GPS-less (vision
position, no global position, PX4 offboard loss -> Hold); outdoor: a global origin
(GLOBAL_POSITION_INT, HOME_POSITION lat/lon, DO_REPOSITION) and PX4's default loss action.

examples:
  onfly sim-vehicle
  onfly sim-vehicle --mavlink udpin:127.0.0.1:14550 --task urban_block-o01 --camera tcp://127.0.0.1:5600
  onfly sim-vehicle --autopilot ardupilot --profile outdoor --scene villa --camera tcp://127.0.0.1:5600 --json vehicle.json
  onfly sim-vehicle --param COM_OBL_RC_ACT=4      (PX4: land on offboard loss)
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from onfly.cli import CliError, echo, task_by_id
from onfly.mavlink.link import LinkError, MavlinkLink
from onfly.mavlink.sim_vehicle import SimMavlinkVehicle, SimVehicleConfig

NAME = "sim-vehicle"
HELP = "serve a simulated PX4/ArduPilot vehicle over MAVLink (for companion tests without hardware)"
DESCRIPTION = __doc__


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--mavlink", default="udpout:127.0.0.1:14540", metavar="URL",
                        help="vehicle link: udpout:HOST:PORT (default, like PX4 SITL), udpin:, tcpin:, tcp:")
    parser.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4", help="which autopilot's rules to follow")
    parser.add_argument("--system-id", type=int, default=1, help="MAVLink system id of the vehicle (default 1)")
    parser.add_argument("--profile", choices=("indoor", "outdoor"), default="indoor", help="GPS-less indoor (default) or outdoor with GPS")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="set an autopilot parameter at boot (repeatable), e.g. COM_OBL_RC_ACT=4, GUID_TIMEOUT=3")
    parser.add_argument("--estimator-yaw-deg", type=float, default=0.0,
                        help="heading of the estimator frame in the scene (a vision estimator starts at an arbitrary heading)")
    parser.add_argument("--telemetry-rate-hz", type=float, default=None,
                        help="LOCAL_POSITION_NED and attitude rate until the companion asks (default: the autopilot's default)")
    parser.add_argument("--duration-s", type=float, default=None, help="stop after this many seconds (default: until Ctrl-C)")
    parser.add_argument("--scene", help="fly in this embedded-world scene (name or file); see `onfly scenes`")
    parser.add_argument("--task", help="start below this benchmark task's start pose (implies its scene); see `onfly tasks list`")
    parser.add_argument("--start", nargs=3, type=float, metavar=("X", "Y", "YAW_DEG"),
                        help="start on the ground here instead of below the scene's / task's start pose (metres, degrees, ENU)")
    parser.add_argument("--camera", metavar="tcp://127.0.0.1:PORT", help="serve the world camera here (needs --scene or --task)")
    parser.add_argument("--camera-rate-hz", type=float, default=2.0, help="camera frames per second (default 2, as the benchmark)")
    parser.add_argument("--width", type=int, default=320, help="camera width in pixels, 90 x 60 deg FOV (default 320)")
    parser.add_argument("--height", type=int, default=214, help="camera height in pixels (default 214)")
    parser.add_argument("--until-landed", action="store_true", help="exit once the vehicle has flown, landed and disarmed")
    parser.add_argument("--json", type=Path, help="write the vehicle's ground truth (collisions, events, trace) here at exit")


def build_world_model(args: argparse.Namespace):
    """The embedded-world model of ``--scene`` / ``--task`` (None without either)."""
    if args.scene is None and args.task is None:
        if args.camera:
            raise CliError("--camera needs --scene or --task (the camera is the embedded world's)")
        return None, None
    from onfly.mavlink.sim_world import WorldVehicleModel
    from onfly.world.scene import SceneFormatError
    from planning.camera import PinholeCamera

    task = task_by_id(args.task) if args.task else None
    if task is not None and args.scene and args.scene != task.scene:
        raise CliError(f"task {task.task_id} is in scene {task.scene!r}, not {args.scene!r}")
    if args.width <= 0 or args.height <= 0:
        raise CliError(f"--width and --height must be positive, got {args.width} x {args.height}")
    camera = PinholeCamera.from_fov(args.width, args.height, 90.0, 60.0)
    scene = task.scene if task is not None else args.scene
    position = yaw = None
    if task is not None:
        position, yaw = task.start.position_m, task.start.yaw_rad
    if getattr(args, "start", None) is not None:
        x, y, yaw_deg = args.start
        height = 1.5 if position is None else float(position[2])  # the ray cast for the ground starts here
        position, yaw = [x, y, height], float(np.deg2rad(yaw_deg))
    try:
        model = WorldVehicleModel.from_scene(scene, position_m=position, yaw_rad=yaw, camera=camera)
    except (SceneFormatError, FileNotFoundError, KeyError, ValueError) as exc:
        raise CliError(f"cannot build the world of {args.task or args.scene!r}: {exc}") from exc
    return model, task


def run(args: argparse.Namespace, stop: threading.Event | None = None, emit: Callable[[str], None] = echo) -> int:
    """Serve until ``--duration-s``, ``--until-landed``, Ctrl-C, or ``stop`` (for in-process use).
    Status lines (the start, each mode or arming change, the exit, a collision) go to ``emit``: the
    CLI's stdout writer by default; an in-process caller passes its own (``list.append``, a log)."""
    params = []
    for item in args.param:
        name, sep, value = item.partition("=")
        try:
            params.append((name.strip(), float(value) if "." in value or "e" in value.lower() else int(value)))
        except ValueError:
            sep = ""
        if not sep:
            raise CliError(f"--param must look like NAME=NUMBER, got {item!r}")
    try:
        config = SimVehicleConfig(autopilot=args.autopilot, profile=args.profile, system_id=args.system_id,
                                  telemetry_rate_hz=args.telemetry_rate_hz, params=tuple(params),
                                  estimator_yaw_rad=float(np.deg2rad(args.estimator_yaw_deg)))
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    if args.duration_s is not None and not args.duration_s > 0:
        raise CliError(f"--duration-s must be positive, got {args.duration_s}")
    if not args.camera_rate_hz > 0:
        raise CliError(f"--camera-rate-hz must be positive, got {args.camera_rate_hz}")
    model, task = build_world_model(args)
    try:
        link = MavlinkLink(args.mavlink, config.system_id, config.component_id)
        link.connect()
    except LinkError as exc:
        raise CliError(str(exc)) from exc
    vehicle = SimMavlinkVehicle(link, config, model=model)
    server = None
    if args.camera:
        from onfly.mavlink.camera_channel import FrameChannelError, FrameServer, parse_tcp_url

        try:
            host, port = parse_tcp_url(args.camera)
            server = FrameServer(lambda: vehicle.observation_in_local(model.observe()), host=host, port=port, rate_hz=args.camera_rate_hz)
        except (FrameChannelError, OSError) as exc:
            link.close()
            raise CliError(f"cannot serve the camera on {args.camera}: {exc}") from exc
    where = "point mass, no camera" if model is None else f"scene {model.world.scene.name}" + (f", task {task.task_id}" if task else "")
    cam = f"; camera {server.url} at {args.camera_rate_hz:g} Hz" if server is not None else ""
    emit(f"onfly sim-vehicle: {args.autopilot} vehicle ({args.profile}, system {config.system_id}) on {args.mavlink}; {where}{cam}")
    t0 = vehicle.clock()
    last_mode = None
    flown = False
    landed_at = None
    trace = []
    if server is not None:
        server.start()
    try:
        with vehicle:
            try:
                while args.duration_s is None or vehicle.clock() - t0 < args.duration_s:
                    if stop is not None and stop.is_set():
                        break
                    mode = (vehicle.mode_name, vehicle.armed)
                    p = vehicle.position_enu()
                    t = vehicle.clock() - t0
                    trace.append([round(t, 3), *(round(float(x), 4) for x in p)])
                    if mode != last_mode:
                        emit(f"t={t:7.2f} s  mode {mode[0]:<14} armed={mode[1]!s:<5} p_enu=({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) m")
                        last_mode = mode
                    flown = flown or (vehicle.armed and not vehicle.model.on_ground)
                    if args.until_landed and flown and not vehicle.armed:
                        if landed_at is None:
                            landed_at = t
                        elif t - landed_at >= 2.0 * config.heartbeat_period_s:  # let the companion see it disarmed
                            emit(f"t={t:7.2f} s  landed and disarmed: exiting")
                            break
                    time.sleep(0.1)
            except KeyboardInterrupt:
                emit("onfly sim-vehicle: stopped")
    finally:
        if server is not None:
            server.stop()
    if model is not None and model.collision is not None:
        c = model.collision
        emit(f"COLLISION with {c.object_name!r} at t={c.t_s:.2f} s (vehicle time since boot)")
    if args.json:
        summary = {
            "autopilot": args.autopilot,
            "task": task.task_id if task else None,
            "world": model.summary() if model is not None else None,
            "time_base": "seconds since the vehicle started (its boot clock)",
            "vehicle_events": [{"t_s": t - t0, "text": e} for t, e in vehicle.events],
            "statustexts": [{"t_s": t - t0, "text": e} for t, e in vehicle.statustexts],
            "params": vehicle.params,
            "setpoints_received": vehicle.setpoints_received,
            "frames_served": server.frames_sent if server is not None else 0,
            "trace_t_x_y_z": trace,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1))
    return 0
