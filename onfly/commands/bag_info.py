"""``onfly bag-info PATH``: what a ROS 1 or ROS 2 bag holds (topics, types, counts, time span)."""

from __future__ import annotations

import argparse
import json
from datetime import datetime, timezone

from onfly.cli import echo


NAME = "bag-info"
HELP = "list the topics, message types, counts and time span of a ROS 1 .bag or ROS 2 bag directory"
DESCRIPTION = (
    "List what a bag holds, like `rosbag info` / `ros2 bag info`, to choose the topics "
    "`onfly replay` reads (depth_topic, rgb_topic, camera_info_topic, pose_topic)."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="ROS 1 .bag file or ROS 2 bag directory (metadata.yaml)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON instead of a table")


def _stamp(ns: int) -> str:
    t = datetime.fromtimestamp(ns / 1e9, tz=timezone.utc)
    return f"{t:%Y-%m-%d %H:%M:%S.%f} UTC ({ns / 1e9:.6f})"


def format_summary(s) -> str:
    """The human-readable table ``onfly bag-info`` prints."""
    lines = [
        f"path:      {s.path}",
        f"format:    {'ROS 1 bag' if s.kind == 'ros1-bag' else 'ROS 2 bag'}",
        f"duration:  {s.duration_s:.3f} s",
        f"start:     {_stamp(s.start_ns)}",
        f"end:       {_stamp(s.end_ns)}",
        f"messages:  {s.messages}",
        "topics:",
    ]
    if not s.topics:
        lines.append("  (none)")
    name_w = max((len(t.name) for t in s.topics), default=0)
    type_w = max((len(t.msgtype) for t in s.topics), default=0)
    for t in s.topics:
        lines.append(f"  {t.name:<{name_w}}  {t.msgtype:<{type_w}}  {t.count:>8} msgs")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from onfly.readers.rosbag import bag_summary

    s = bag_summary(args.path)
    if args.json:
        echo(
            json.dumps(
                {
                    "path": str(s.path),
                    "kind": s.kind,
                    "start_ns": s.start_ns,
                    "end_ns": s.end_ns,
                    "duration_s": s.duration_s,
                    "messages": s.messages,
                    "topics": [{"name": t.name, "type": t.msgtype, "count": t.count} for t in s.topics],
                },
                indent=2,
            )
        )
    else:
        echo(format_summary(s))
    return 0
