"""``onfly fly``: fly an instruction onboard, through a MAVLink autopilot (PX4 or ArduPilot).

The companion side of a real flight: connects to the autopilot, engages it (PX4 offboard or
ArduPilot guided), takes off, runs the OnFly pilot at 10 Hz on the camera's newest frame and
the autopilot's odometry, and when the pilot declares its STOP holds (PX4: switched to Hold;
ArduPilot: a position target in GUIDED) or lands over ground its map shows clear. Every
failsafe event is written with its time and cause to the ``--json`` summary; ``--log DIR``
writes the OnFly log (`onfly replay DIR`, `onfly export DIR --out BAG`), ``--rrd`` a rerun
recording. See ``onfly/onboard.py`` for phases and failsafes and docs/flight.md.

The pilot's world frame is anchored at the vehicle's estimated pose when the flight starts
(x along its heading, z up): heights, --volume and the log are relative to the take-off point.

Without hardware, fly against ``onfly sim-vehicle`` (the embedded world as a MAVLink vehicle):

  onfly sim-vehicle --mavlink udpin:127.0.0.1:14550 --task urban_block-o01 --camera tcp://127.0.0.1:5600 &
  onfly fly --connect udpout:127.0.0.1:14550 --camera tcp://127.0.0.1:5600 --task urban_block-o01 --vlm sim:perfect \\
            --on-finish land --log runs/flight-log --rrd runs/flight.rrd --json runs/flight.json

More examples:
  onfly fly --connect udpin:0.0.0.0:14540 --camera realsense --vlm http://127.0.0.1:8000#Qwen2.5-VL-3B \\
            --instruction "fly through the gate, then stop next to the red van"
  onfly fly --connect serial:/dev/ttyTHS1:921600 --autopilot ardupilot --camera runs/log1 --instruction "..."

--camera takes tcp://HOST:PORT (a simulated vehicle's camera), realsense (pip install
onfly[realsense]) or a recording (OnFly log, TUM folder, ROS bag) played at real time.
With a simulated VLM (--vlm sim:...) each answer lands after its modelled latency on the wall
clock (--modelled-latency auto), as the benchmark charges it on its virtual clock.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path

from onfly.cli import CliError, echo, task_by_id

NAME = "fly"
HELP = "fly an instruction onboard through a MAVLink autopilot (PX4 offboard / ArduPilot guided)"
DESCRIPTION = __doc__

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--connect", required=True, metavar="URL", help="autopilot link: udpin:HOST:PORT, udpout:, tcp:, serial:DEV[:BAUD]")
    p.add_argument("--instruction", help="the instruction to fly")
    p.add_argument("--task", help="a benchmark task id: its instruction, take-off height and (in the summary) its metrics")
    p.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4", help="PX4 offboard (default) or ArduPilot guided")
    p.add_argument("--vlm", default="sim:nominal", help="sim:<preset> | http:<url>[#model] | transformers:<dir> (default sim:nominal)")
    p.add_argument("--seed", type=int, default=0, help="seed of a simulated VLM (default 0)")
    p.add_argument("--camera", help="tcp://HOST:PORT | realsense | a recording path (default: none, the pilot holds)")
    p.add_argument("--config", type=Path, help="TOML with a [pilot] table of PilotConfig overrides")
    p.add_argument("--modelled-latency", choices=("auto", "on", "off"), default="auto",
                   help="land each VLM answer after its modelled latency (auto: on for sim: backends)")
    p.add_argument("--system-id", type=int, default=1, help="MAVLink system id of the vehicle (default 1)")
    p.add_argument("--takeoff-alt-m", type=float, default=None, help="climb this far above the engage position (default 1.5, or the task's start height)")
    p.add_argument("--time-limit-s", type=float, default=70.0, help="mission time limit after the start (paper: 70 s)")
    p.add_argument("--hold-s", type=float, default=2.0, help="hold after the STOP before --on-finish (default 2 s)")
    p.add_argument("--on-finish", choices=("hold", "land"), default="hold",
                   help="hold: leave the vehicle holding (default); land: over the nearest ground the map shows clear")
    p.add_argument("--volume", metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
                   help="operator flight volume in the flight's world frame (metres from the take-off point); also `volume` in --config")
    p.add_argument("--start", nargs=3, type=float, metavar=("X", "Y", "YAW_DEG"),
                   help="with --task: where the vehicle started in the task's scene (as `sim-vehicle --start`), to score the flight; default the task's start")
    p.add_argument("--json", type=Path, help="write the flight summary (failsafes, events, metrics, trace) here")
    p.add_argument("--log", type=Path, metavar="DIR", help="write the OnFly log (frames, pilot and flight events, failsafes) to this new folder")
    p.add_argument("--rrd", type=Path, help="write a rerun recording of the flight here")


def run(args: argparse.Namespace) -> int:
    from onfly.mavlink.autopilot import OffboardConfig, make_session
    from onfly.mavlink.bridge import BridgeConfig, BridgeError, MavlinkBridge, SafetyLimits
    from onfly.mavlink.link import LinkError
    from onfly.onboard import GroundTruth, OnboardConfig, OnboardFlight, pose_source
    from onfly.pilot import OnFlyPilot, PilotConfig
    from onfly.readers.realtime import MonotonicClock
    from onfly.runtime import ThreadRuntime
    from onfly.sources.camera import CameraError, open_camera
    from vlm.factory import make_backend

    task = task_by_id(args.task) if args.task else None
    volume = _volume(args)
    if args.log is not None and args.log.exists():
        raise CliError(f"--log {args.log} already exists; choose a new folder")
    if task is None and not args.instruction:
        raise CliError("give --instruction TEXT or --task ID")
    instruction = args.instruction or task.instruction
    takeoff = args.takeoff_alt_m if args.takeoff_alt_m is not None else (float(task.start.position_m[2]) if task else 1.5)
    try:
        config = OnboardConfig(
            takeoff_alt_m=takeoff, time_limit_s=args.time_limit_s, hold_after_finish_s=args.hold_s, on_finish=args.on_finish
        )
        pilot_config = _fly_config(args.config)[0] if args.config else PilotConfig()
        # the setpoints leave the companion under the planner's own limits and the volume
        pc = pilot_config.planner
        limits = SafetyLimits.for_vehicle(pc.v_max_mps, pc.a_max_mps2, volume)
        bridge_config = BridgeConfig(target_system=args.system_id, source_system=args.system_id, limits=limits)
        offboard = OffboardConfig(takeoff_alt_m=max(takeoff, 0.5))
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    honour = args.modelled_latency == "on" or (args.modelled_latency == "auto" and args.vlm.strip().lower().startswith("sim:"))
    ground_truth = None
    if task is not None:
        ground_truth = GroundTruth(task.goal_region, task.reference.path_length_m if task.reference else 0.0, task_id=task.task_id,
                                   T_scene_world=_task_start_frame(task, args.start))

    clock = MonotonicClock()
    backend = make_backend(args.vlm, seed=args.seed)  # ValueError names the valid specs
    runtime = ThreadRuntime(clock.now_s, honour_modelled_latency=honour)
    echo(f"onfly fly: building the pilot (planner set-up) ...")
    pilot = OnFlyPilot(pilot_config, backend, runtime, volume=volume)
    try:
        bridge = MavlinkBridge.from_url(args.connect, bridge_config, clock=clock.now_s)
        bridge.start()
    except (LinkError, BridgeError, OSError) as exc:
        runtime.close()
        raise CliError(f"cannot open the autopilot link {args.connect}: {exc}") from exc
    camera = writer = recorder = None
    try:
        if args.camera:
            try:
                camera = open_camera(args.camera, clock=clock, pose_source=pose_source(bridge)).start()
            except CameraError as exc:
                raise CliError(str(exc)) from exc
        else:
            echo("onfly fly: no --camera: the pilot gets no frames and will hold")
        session = make_session(args.autopilot, bridge, offboard)
        if args.log is not None:
            from onfly.logs.writer import LogWriter

            writer = LogWriter(args.log, meta={"instruction": instruction, "task": args.task, "vlm": args.vlm, "seed": args.seed,
                                               "source": "onfly fly", "autopilot": args.autopilot, "connect": args.connect,
                                               "frame": "flight world: anchored at the estimator pose at the start"})
        if args.rrd is not None:
            from onfly.viz import RerunRecorder

            recorder = RerunRecorder(args.rrd)
        flight = OnboardFlight(bridge, session, pilot, camera, instruction, config, clock=clock, ground_truth=ground_truth,
                               writer=writer, recorder=recorder)
        echo(f"onfly fly: {args.autopilot} on {args.connect}; vlm {args.vlm} (modelled latency {'on' if honour else 'off'}); "
             f"camera {args.camera or 'none'}; instruction: {instruction}")
        try:
            summary = flight.run()
        except BridgeError as exc:
            raise CliError(f"could not fly: {exc}") from exc
    finally:
        bridge.stop()
        if camera is not None:
            camera.close()
        runtime.close()
        backend.close()
        if writer is not None:
            writer.close()
        if recorder is not None:
            recorder.close()

    echo(f"end        {summary.end_reason}   pilot finished {summary.finished}   flight {summary.flight_time_s:.1f} s   take-off {summary.takeoff_s:.1f} s")
    if summary.metrics:
        m = summary.metrics
        echo(f"task       {m['task']}   success {m['success']}   NE {m['navigation_error_m']:.2f} m   path {m['path_length_m']:.1f} m   SPL {m['spl']:.2f}")
    active = [f for f in summary.failsafes if not f["cleared"]]
    echo(f"failsafes  {len(active)} raised: " + (", ".join(f"{f['cause']}@{f['t_s']:.2f}s" for f in active[:8]) or "none"))
    echo(f"landing    {'landed and disarmed' if summary.landed else 'not landed'}   crashed {summary.crashed}")
    echo(f"loop       ticks {summary.loop['ticks']}  overruns {summary.loop['overruns']}  tick p95 {summary.loop['tick_ms_p95']:.0f} ms  "
         f"camera frames {summary.camera.get('received', 0)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        out = {"connect": args.connect, "vlm": args.vlm, "seed": args.seed, "camera": args.camera, "honour_modelled_latency": honour,
               "onboard_config": dataclasses.asdict(config), **summary.to_dict()}
        args.json.write_text(json.dumps(out, indent=1, default=str))
    if args.log is not None:
        echo(f"log        {args.log}   (replay: onfly replay {args.log}; export: onfly export {args.log} --out BAG)")
    if args.rrd is not None:
        echo(f"recording  {args.rrd}   (open with: rerun {args.rrd})")
    return 0 if summary.end_reason in ("finished", "time_limit") and not summary.crashed else 1


def _volume(args):
    """The operator volume of --volume or the config's ``volume`` key (a string or six numbers)."""
    from planning.volume import FlightVolume, FlightVolumeError

    text = args.volume
    if text is None and args.config is not None:
        raw = _fly_config(args.config)[1]
        if raw is not None:
            text = ",".join(str(v) for v in raw) if isinstance(raw, (list, tuple)) else str(raw)
    if text is None:
        return None
    try:
        return FlightVolume.parse(text)
    except FlightVolumeError as exc:
        raise CliError(f"--volume: {exc}") from exc


#: What a ``fly --config`` file may hold: the pilot's table and the operator volume (top level
#: or in a ``[fly]`` table).
FLY_CONFIG_KEYS = ("pilot", "fly", "volume")


def _fly_config(path):
    """``(PilotConfig, volume or None)`` of a ``fly --config`` file; unknown tables and keys are
    errors naming the file and the key (CliError)."""
    from onfly.pilot import PilotConfig
    from onfly.serialize import ConfigFileError, read_toml

    try:
        data = read_toml(path)
    except ConfigFileError as exc:
        raise CliError(str(exc)) from exc
    bad = sorted(set(data) - set(FLY_CONFIG_KEYS))
    if bad:
        raise CliError(f"{path}: unknown table(s) or key(s) {bad}; valid: {list(FLY_CONFIG_KEYS)}")
    for table in ("pilot", "fly"):
        if table in data and not isinstance(data[table], dict):
            raise CliError(f"{path}: {table!r} must be a table ([{table}])")
    fly = data.get("fly", {})
    if sorted(set(fly) - {"volume"}):
        raise CliError(f"{path}: unknown key(s) in [fly] {sorted(set(fly) - {'volume'})}; valid: ['volume']")
    if "volume" in data and "volume" in fly:
        raise CliError(f"{path}: 'volume' given both at the top level and in [fly]")
    try:
        pilot = PilotConfig.from_dict(data.get("pilot", {}))
    except ValueError as exc:
        raise CliError(f"{path}: [pilot]: {exc}") from exc
    return pilot, data.get("volume", fly.get("volume"))


def _task_start_frame(task, start=None):
    """T_scene_world (4, 4) of a flight anchored at the task's start: the start pose's x, y and
    heading on the ground below it (where `onfly sim-vehicle --task` puts the vehicle). Used only
    to score the flown trace against the task's goal region."""
    import numpy as np

    from onfly.mavlink.sim_world import ground_below
    from onfly.world.world import World

    p = np.asarray(task.start.position_m, dtype=float)
    yaw = task.start.yaw_rad
    if start is not None:
        p, yaw = np.array([start[0], start[1], p[2]]), float(np.deg2rad(start[2]))
    ground = ground_below(World.from_scene(task.scene), p)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [p[0], p[1], ground]
    return T


if __name__ == "__main__":  # pragma: no cover
    from onfly.cli import main

    sys.exit(main(["fly", *sys.argv[1:]]))
