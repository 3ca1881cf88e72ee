"""``onfly replay --tf-parent / --tf-child``: a bag whose poses are on /tf replays from the
command line; without the flags the error names the flags, not reader fields."""

from __future__ import annotations

import json
from itertools import islice

from onfly.cli import main
from onfly.readers.tum import TumReader
from realdata_paths import REALDATA
from test_rosbag_reader import write_bag

KITCHEN = REALDATA / "7scenes-kitchen-tum"


def test_tf_bag_replays_with_the_frame_flags(tmp_path, capsys):
    obs = list(islice(TumReader(KITCHEN), 3))
    bag = write_bag(tmp_path / "tf.bag", obs, ros2=False, depth_encoding="32FC1", pose_type="tf")
    rc = main(["replay", str(bag), "--pose-topic", "/tf", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert "pass --tf-parent and --tf-child" in err and "tf_parent_frame" not in err
    out_json = tmp_path / "r.json"
    rc = main(["replay", str(bag), "--pose-topic", "/tf", "--tf-parent", "world", "--tf-child", "camera",
               "--goal", "-0.5,0,1", "--no-progress", "--json", str(out_json)])
    assert rc == 0, capsys.readouterr().err
    r = json.loads(out_json.read_text())
    assert r["frames"] == 3
    assert all(f["goal_m"] == [-0.5, 0.0, 1.0] for f in r["per_frame"])  # a negative number reached --goal
