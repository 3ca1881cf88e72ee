"""``onfly replay``: the real 7-Scenes kitchen recording end to end (table, JSON, rerun file
checked by ``rerun rrd verify``), and user errors as one line with exit status 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from onfly.cli import main
from realdata_paths import REALDATA

KITCHEN = REALDATA / "7scenes-kitchen-tum"
RERUN = Path(sys.executable).parent / "rerun"


def _one_line_error(capsys, argv, match: str) -> str:
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("onfly replay: error: ")
    assert "Traceback" not in err
    assert match in lines[0], lines[0]
    return lines[0]


def test_kitchen_replays_end_to_end_with_json_and_a_valid_rerun_file(tmp_path, capsys):
    out_json, out_rrd = tmp_path / "out.json", tmp_path / "out.rrd"
    rc = main(["replay", str(KITCHEN), "--json", str(out_json), "--rrd", str(out_rrd), "--no-progress"])
    out, _ = capsys.readouterr()
    assert rc == 0
    report = json.loads(out_json.read_text())
    assert report["frames"] == 60 and report["frames_read"] == 60
    assert report["kind"] == "tum" and report["goal_mode"] == "future_pose"
    assert set(report["latency_ms"]) == {"esdf", "planner"}
    for lat in report["latency_ms"].values():
        assert set(lat) == {"n", "median_ms", "p95_ms", "max_ms"} and lat["n"] == 60
        assert 0 < lat["median_ms"] <= lat["p95_ms"] <= lat["max_ms"]
    # the Kinect camera was never inside an obstacle of the map built from its own depth;
    # distances are clamped at EsdfConfig.max_distance_m (1 m)
    assert 0 < report["path_clearance_min_m"] <= report["path_clearance_median_m"] <= 1.0
    clearances = [f["path_clearance_m"] for f in report["per_frame"]]
    assert len(clearances) == 60 and min(clearances) == report["path_clearance_min_m"]
    assert report["planner_slack_steps"] + sum(report["planner_fallbacks"].values()) <= 60
    # the log lasts 1.97 s < 3 s: every future-pose goal is the last logged position
    last = report["per_frame"][-1]["position_m"]
    assert all(f["goal_m"] == last for f in report["per_frame"])
    assert "path clearance    min" in out and "esdf" in out and str(out_json) in out
    verify = subprocess.run([str(RERUN), "rrd", "verify", str(out_rrd)], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr
    assert "without error" in verify.stdout + verify.stderr


def test_config_file_sets_goal_and_frame_limit(tmp_path, capsys):
    cfg = tmp_path / "replay.toml"
    cfg.write_text('[replay]\ngoal_mode = "fixed"\ngoal_world = [0.0, 0.5, 1.0]\nmax_frames = 3\n[replay.planner]\nv_max_mps = 0.3\n')
    out_json = tmp_path / "out.json"
    assert main(["replay", str(KITCHEN), "--config", str(cfg), "--every", "5", "--json", str(out_json), "--no-progress"]) == 0
    capsys.readouterr()
    r = json.loads(out_json.read_text())
    assert [f["index"] for f in r["per_frame"]] == [0, 5, 10]
    assert all(f["goal_m"] == [0.0, 0.5, 1.0] for f in r["per_frame"])
    assert r["config"]["planner"]["v_max_mps"] == 0.3 and r["config"]["every_n"] == 5


def test_bad_config_file_is_one_line(tmp_path, capsys):
    cfg = tmp_path / "replay.toml"
    cfg.write_text("[replay]\nspeed = 2\n")
    _one_line_error(capsys, ["replay", str(KITCHEN), "--config", str(cfg)], "unknown replay option 'speed'")
    cfg.write_text("[replay\n")
    _one_line_error(capsys, ["replay", str(KITCHEN), "--config", str(cfg)], "not valid TOML")


def test_missing_folder_is_one_line(tmp_path, capsys):
    _one_line_error(capsys, ["replay", str(tmp_path / "nope")], "nope: no such file or directory")


def test_not_a_recording_is_one_line(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("hello")
    _one_line_error(capsys, ["replay", str(tmp_path)], "not a recognised observation source")


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--goal", "1,2"], "--goal must be 3 comma-separated finite numbers"),
        (["--goal", "1,2,3", "--future-pose-s", "2"], "either --goal or --future-pose-s"),
        (["--every", "0"], "--every must be a positive integer"),
        (["--future-pose-s", "-1"], "--future-pose-s must be a positive number"),
        (["--intrinsics", "585,585,320"], "--intrinsics (fx,fy,cx,cy) must be 4"),
        (["--depth-topic", "/depth"], "option(s) --depth-topic do not apply to a tum source"),
        (["--vlm", "gpt4"], "vlm must be a backend spec"),
        (["--instruction", "go", "--vlm", "tiny:llama"], "tiny model family must be one of"),
    ],
)
def test_bad_options_are_one_line(capsys, extra, match):
    _one_line_error(capsys, ["replay", str(KITCHEN), "--no-progress", *extra], match)


def test_simulated_vlm_on_a_real_recording_is_one_line(capsys):
    line = _one_line_error(
        capsys, ["replay", str(KITCHEN), "--instruction", "fly to the kettle", "--vlm", "sim:perfect", "--no-progress"], "annotations"
    )
    assert "--vlm http:URL" in line and "--vlm tiny" in line


def test_unreachable_vlm_server_is_one_line(capsys):
    _one_line_error(
        capsys,
        ["replay", str(KITCHEN), "--instruction", "fly to the kettle", "--vlm", "http:127.0.0.1:9", "--no-progress"],
        "--vlm: VLM backend 'http:127.0.0.1:9' cannot be reached: connection refused",
    )


def _tiny_ros1_bag(path: Path) -> Path:
    """One 4 x 3 depth image, one colour image and one odometry message."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    T = store.types
    header = T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")

    def image(arr, encoding):
        data = np.ascontiguousarray(arr).view(np.uint8).reshape(-1)
        return T["sensor_msgs/msg/Image"](
            header=header, height=3, width=4, encoding=encoding, is_bigendian=0, step=data.size // 3, data=data
        )

    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    )
    cov = np.zeros(36)
    odom = T["nav_msgs/msg/Odometry"](
        header=header,
        child_frame_id="cam",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0), angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
            covariance=cov,
        ),
    )
    with Writer(path) as writer:
        for topic, msgtype, msg in (
            ("/camera/depth/image_raw", "sensor_msgs/msg/Image", image(np.full((3, 4), 2.0, np.float32), "32FC1")),
            ("/camera/color/image_raw", "sensor_msgs/msg/Image", image(np.zeros((3, 4, 3), np.uint8), "rgb8")),
            ("/odom", "nav_msgs/msg/Odometry", odom),
        ):
            conn = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conn, 1_000_000_000, store.serialize_ros1(msg, msgtype))
    return path


def test_bag_without_the_named_topic_is_one_line(tmp_path, capsys):
    bag = _tiny_ros1_bag(tmp_path / "tiny.bag")
    line = _one_line_error(
        capsys, ["replay", str(bag), "--pose-topic", "/vicon/pose", "--intrinsics", "2,2,2,1.5", "--no-progress"], "no topic /vicon/pose for pose"
    )
    assert "/odom (nav_msgs/msg/Odometry)" in line  # the listing names what the bag does hold


@pytest.mark.slow
def test_kitchen_with_an_instruction_runs_the_tiny_random_model_through_the_pipeline(tmp_path, capsys):
    out_json = tmp_path / "tiny.json"
    rc = main(
        ["replay", str(KITCHEN), "--instruction", "fly to the kettle, then stop at the sink", "--vlm", "tiny",
         "--every", "20", "--json", str(out_json), "--no-progress"]
    )
    capsys.readouterr()
    assert rc == 0
    r = json.loads(out_json.read_text())
    assert r["frames"] == 3 and r["goal_mode"] == "agents" and r["vlm_latency"] == "measured"
    assert {"decision_vlm", "monitoring_vlm", "features", "esdf", "planner"} <= set(r["latency_ms"])
    assert r["decisions"] == 3
    # a random-weight model answers garbage: every decision fails to parse and the vehicle holds
    assert r["goals_accepted"] == 0 and r["decision_failures"] == {"parse": 3}
    assert all(f["goal_m"] == f["position_m"] for f in r["per_frame"])
    # one vision-encoder pass per frame, shared by the decision prompt, the monitoring prompt
    # and the verifier's features
    assert r["vision_runs_max_per_frame"] == 1 and r["vision_runs_mean_per_frame"] == 1.0
