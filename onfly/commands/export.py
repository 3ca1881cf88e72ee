"""``onfly export LOG --out BAG``: an OnFly log (``onfly fly --log``, ``onfly run --log``) as a
ROS 2 bag, MCAP (default) or SQLite 3 storage, written with rosbags (no ROS install).

Topics (stamps: the log's clock, seconds -> nanoseconds; frame ids ``world`` and ``camera``)
------------------------------------------------------------------------------------------
``/camera/color/image_raw``     sensor_msgs/msg/Image, rgb8
``/camera/depth/image_raw``     sensor_msgs/msg/Image, 32FC1 z-depth in metres (0/NaN: no reading)
``/camera/depth/camera_info``   sensor_msgs/msg/CameraInfo, pinhole, no distortion
``/camera/pose``                geometry_msgs/msg/PoseStamped, camera optical frame in ``world``
``/onfly/events``               std_msgs/msg/String, one JSON object per log event
``/vehicle/pose``               geometry_msgs/msg/PoseStamped, the vehicle trace of a flight
                                summary (``--summary fly.json``), position only

`onfly bag-info` lists it; `onfly replay BAG` reads it back (the topics above are the ones its
automatic topic choice picks).

examples:
  onfly export runs/flight-log --out runs/flight.mcap
  onfly export runs/flight-log --out runs/flight-bag --storage sqlite3 --summary runs/fly.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from onfly.cli import CliError, echo

NAME = "export"
HELP = "export an OnFly log (a flight's or a run's) as a ROS 2 bag (MCAP or SQLite 3) through rosbags"
DESCRIPTION = __doc__

TOPICS = {
    "rgb": "/camera/color/image_raw",
    "depth": "/camera/depth/image_raw",
    "camera_info": "/camera/depth/camera_info",
    "pose": "/camera/pose",
    "events": "/onfly/events",
    "vehicle": "/vehicle/pose",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("log", type=Path, help="OnFly log directory (meta.json, frames.bin, events.jsonl)")
    parser.add_argument("--out", type=Path, required=True, help="the bag directory to create (must not exist)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="ROS 2 storage plugin (default mcap)")
    parser.add_argument("--summary", type=Path, help="an `onfly fly --json` summary: its vehicle trace becomes /vehicle/pose")


def _stamp(t_s: float, time_cls):
    ns = int(round(max(0.0, float(t_s)) * 1e9))
    return time_cls(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), ns


def export_log(log_dir: Path, out: Path, storage: str = "mcap", summary: dict | None = None) -> dict[str, int]:
    """Write the bag; returns {topic: message count}. Raises CliError for a missing or bad log
    and an existing output."""
    import numpy as np
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from onfly.logs.format import LogError
    from onfly.logs.reader import LogReader
    from planning.frames import quat_from_matrix

    if out.exists():
        raise CliError(f"--out {out} already exists; choose a new bag directory")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    Image, CameraInfo = ts.types["sensor_msgs/msg/Image"], ts.types["sensor_msgs/msg/CameraInfo"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    PoseStamped, Pose = ts.types["geometry_msgs/msg/PoseStamped"], ts.types["geometry_msgs/msg/Pose"]
    Point, Quaternion = ts.types["geometry_msgs/msg/Point"], ts.types["geometry_msgs/msg/Quaternion"]
    String, RoI = ts.types["std_msgs/msg/String"], ts.types["sensor_msgs/msg/RegionOfInterest"]
    counts = {t: 0 for t in TOPICS.values()}
    try:
        reader = LogReader(log_dir)
    except (LogError, FileNotFoundError, OSError) as exc:
        raise CliError(f"cannot read the OnFly log {log_dir}: {exc}") from exc
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with reader, Writer(out, version=9, storage_plugin=plugin) as writer:
        conns = {}
        types = {"rgb": Image, "depth": Image, "camera_info": CameraInfo, "pose": PoseStamped, "events": String, "vehicle": PoseStamped}
        for role, topic in TOPICS.items():
            if role == "vehicle" and summary is None:
                continue
            conns[role] = writer.add_connection(topic, types[role].__msgtype__, typestore=ts)

        def put(role, msg, ns):
            writer.write(conns[role], ns, ts.serialize_cdr(msg, types[role].__msgtype__))
            counts[TOPICS[role]] += 1

        try:
            for frame in reader.frames():
                obs = frame.observation
                stamp, ns = _stamp(obs.t_s, Time)
                h, w = obs.depth_m.shape
                cam = obs.camera
                head_cam = Header(stamp=stamp, frame_id="camera")
                rgb = np.ascontiguousarray(obs.rgb, dtype=np.uint8)
                put("rgb", Image(header=head_cam, height=h, width=w, encoding="rgb8", is_bigendian=0, step=w * 3,
                                 data=rgb.reshape(-1)), ns)
                depth = np.ascontiguousarray(obs.depth_m, dtype="<f4")
                put("depth", Image(header=head_cam, height=h, width=w, encoding="32FC1", is_bigendian=0, step=w * 4,
                                   data=depth.view(np.uint8).reshape(-1)), ns)
                K = np.array([cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0])
                P = np.array([cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
                put("camera_info", CameraInfo(header=head_cam, height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5), k=K,
                                              r=np.eye(3).reshape(-1), p=P, binning_x=0, binning_y=0,
                                              roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)), ns)
                T = np.asarray(obs.T_world_cam, dtype=float)
                q = quat_from_matrix(T[:3, :3])  # (w, x, y, z)
                put("pose", PoseStamped(header=Header(stamp=stamp, frame_id="world"), pose=Pose(
                    position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                    orientation=Quaternion(x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])))), ns)
            for ev in reader.events():
                _, ns = _stamp(ev.t_s, Time)
                text = json.dumps({"seq": ev.seq, "t_s": ev.t_s, "kind": ev.kind, "frame_index": ev.frame_index, "data": ev.data},
                                  default=str)
                put("events", String(data=text), ns)
        except LogError as exc:
            raise CliError(f"the OnFly log {log_dir} is damaged: {exc}") from exc
        if summary is not None:
            t_abs = summary.get("t_begin_abs_s", 0.0) or 0.0
            for row in summary.get("trace_t_x_y_z", []):
                t, x, y, z = (float(v) for v in row[:4])
                stamp, ns = _stamp(t_abs + t, Time)
                put("vehicle", PoseStamped(header=Header(stamp=stamp, frame_id="world"), pose=Pose(
                    position=Point(x=x, y=y, z=z), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))), ns)
    return counts


def run(args: argparse.Namespace) -> int:
    summary = None
    if args.summary is not None:
        try:
            summary = json.loads(args.summary.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise CliError(f"--summary {args.summary}: {exc}") from exc
        if not isinstance(summary, dict) or "trace_t_x_y_z" not in summary:
            raise CliError(f"--summary {args.summary} is not an `onfly fly --json` summary (no trace_t_x_y_z)")
    counts = export_log(args.log, args.out, args.storage, summary)
    echo(f"wrote {args.out} ({args.storage}):")
    for topic, n in counts.items():
        if n:
            echo(f"  {topic:<28} {n:>6} msgs")
    return 0
