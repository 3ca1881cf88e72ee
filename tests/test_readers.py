"""One interface over logs, TUM folders and bags (open_source), and real-time playback."""

from __future__ import annotations

from itertools import islice
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from onfly.logs import LogReader, LogWriter
from onfly.observation import Observation
from onfly.readers import (
    BagConfig,
    BagFormatError,
    BagReader,
    ObservationSource,
    RealtimeConfig,
    RealtimeSource,
    SourceKindError,
    TumReader,
    detect_kind,
    known_length,
    open_source,
)
from planning.camera import PinholeCamera
from realdata_paths import REALDATA

KITCHEN = REALDATA / "7scenes-kitchen-tum"


def _depth_only_bag(path: Path, ros2: bool) -> Path:
    """A bag with one 32FC1 image topic and nothing else."""
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    hdr = Header(stamp=Time(sec=1, nanosec=0), frame_id="cam") if ros2 else Header(seq=0, stamp=Time(sec=1, nanosec=0), frame_id="cam")
    img = store.types["sensor_msgs/msg/Image"](
        header=hdr, height=2, width=2, encoding="32FC1", is_bigendian=0, step=8, data=np.zeros(16, np.uint8)
    )
    writer = Writer2(path, version=9) if ros2 else Writer1(path)
    with writer:
        conn = writer.add_connection("/depth", "sensor_msgs/msg/Image", typestore=store)
        writer.write(conn, 1_000_000_000, (store.serialize_cdr if ros2 else store.serialize_ros1)(img, "sensor_msgs/msg/Image"))
    return path


def test_detect_kind_of_each_source(tmp_path):
    frames = list(islice(TumReader(KITCHEN), 2))
    with LogWriter(tmp_path / "log") as w:
        for o in frames:
            w.write(o)
    assert detect_kind(tmp_path / "log") == "onfly-log"
    assert detect_kind(KITCHEN) == "tum"
    assert detect_kind(_depth_only_bag(tmp_path / "a.bag", ros2=False)) == "ros1-bag"
    assert detect_kind(_depth_only_bag(tmp_path / "b", ros2=True)) == "ros2-bag"
    db3 = next((tmp_path / "b").glob("*.db3"))
    assert detect_kind(db3) == "ros2-bag"


def test_undetectable_paths_list_the_valid_kinds(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceKindError, match=r"empty: not a recognised observation source \(expected one of: OnFly log directory .*TUM RGB-D folder .*ROS 1 bag file .*ROS 2 bag directory"):
        open_source(tmp_path / "empty")
    with pytest.raises(SourceKindError, match=r"missing: no such file or directory"):
        open_source(tmp_path / "missing")
    with pytest.raises(SourceKindError, match=r"unknown source kind 'zip' \(valid: onfly-log, tum, ros1-bag, ros2-bag\)"):
        open_source(KITCHEN, kind="zip")


def test_open_source_reads_a_log_and_a_tum_folder_to_the_same_observations(tmp_path):
    with open_source(KITCHEN, max_difference_s=0.01, depth_topic=None) as tum:
        assert isinstance(tum, TumReader) and isinstance(tum, ObservationSource)
        assert tum.kind == "tum" and known_length(tum) == 60
        frames = list(islice(tum, 3))
    with LogWriter(tmp_path / "log") as w:
        for o in frames:
            w.write(o)
    with open_source(tmp_path / "log") as log:
        assert isinstance(log, LogReader) and isinstance(log, ObservationSource)
        assert known_length(log) == 3
        for a, b in zip(log, frames):
            assert a.t_s == b.t_s and a.depth_m.tobytes() == b.depth_m.tobytes() and a.rgb.tobytes() == b.rgb.tobytes()
            np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)


def test_options_are_checked_against_the_kind(tmp_path):
    with pytest.raises(SourceKindError, match=r"option\(s\) depth_topic do not apply to a tum source \(valid: .*depth_scale.*max_difference_s"):
        open_source(KITCHEN, depth_topic="/d")
    with LogWriter(tmp_path / "log"):
        pass
    with pytest.raises(SourceKindError, match=r"option\(s\) depth_scale do not apply to an onfly-log source"):
        open_source(tmp_path / "log", depth_scale=1000.0)
    cam = open_source(KITCHEN, intrinsics=(500.0, 500.0, 319.5, 239.5)).camera
    assert (cam.fx, cam.cx) == (500.0, 319.5)


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_open_source_forwards_bag_options(tmp_path, ros2):
    path = _depth_only_bag(tmp_path / ("rec" if ros2 else "rec.bag"), ros2)
    with pytest.raises(BagFormatError, match=r"no topic /camera/depth for depth \(topics: /depth \(sensor_msgs/msg/Image\)\)"):
        open_source(path, depth_topic="/camera/depth")
    # the only image topic is the depth: no colour topic to choose
    with pytest.raises(BagFormatError, match=r"no topic for rgb found; pass rgb_topic"):
        open_source(path, depth_topic="/depth")
    with pytest.raises(BagFormatError, match=r"no topic /rgb for rgb"):
        BagReader(path, BagConfig(depth_topic="/depth", rgb_topic="/rgb"))


# -- real-time playback --------------------------------------------------------------------------


class FakeClock:
    """A clock the test drives: sleeping jumps to the wake-up time and is recorded."""

    def __init__(self, t0: float = 100.0) -> None:
        self.t = t0
        self.sleeps: list[float] = []

    def now_s(self) -> float:
        return self.t

    def sleep_until_s(self, t_s: float) -> None:
        self.sleeps.append(t_s)
        self.t = max(self.t, t_s)


class ListSource:
    kind = "list"
    path = Path("memory")

    def __init__(self, observations):
        self.observations = observations
        self.closed = False

    def __iter__(self):
        return iter(self.observations)

    def __len__(self):
        return len(self.observations)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self.closed = True


def _frames(times):
    cam = PinholeCamera.from_fov(4, 3)
    return [Observation(t, np.zeros((3, 4, 3), np.uint8), np.ones((3, 4), np.float32), np.eye(4), cam, f"f{k}") for k, t in enumerate(times)]


@pytest.mark.parametrize("speed", [1.0, 2.0, 0.5])
def test_realtime_releases_frames_at_recorded_pace(speed):
    times = [10.0, 10.1, 10.25, 11.0]
    clock = FakeClock()
    src = RealtimeSource(ListSource(_frames(times)), RealtimeConfig(speed=speed), clock)
    released = []
    for obs in src:
        released.append((obs.t_s, clock.now_s()))
    assert [t for t, _ in released] == times  # recorded stamps kept by default
    expected = [100.0 + (t - times[0]) / speed for t in times]
    np.testing.assert_allclose([c for _, c in released], expected, atol=1e-12)
    np.testing.assert_allclose(clock.sleeps, expected[1:], atol=1e-12)
    assert len(src) == 4 and src.dropped == 0


def test_realtime_drops_frames_a_slow_consumer_missed_and_restamps():
    clock = FakeClock(0.0)
    times = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    src = RealtimeSource(ListSource(_frames(times)), RealtimeConfig(drop_late_s=0.06, restamp=True), clock)
    got = []
    for obs in src:
        got.append(obs)
        clock.t += 0.25  # processing a frame takes 0.25 s
    # f0 at 0; at 0.25 f1 (0.15 s late) is dropped, f2 (0.05 s late) kept; at 0.5 f3, f4
    # (0.2, 0.1 s late) dropped, f5 on time
    assert [o.frame_id for o in got] == ["f0", "f2", "f5"]
    assert src.dropped == 3
    assert [o.t_s for o in got] == [0.0, 0.25, 0.5]  # restamped to the clock


def test_realtime_config_is_validated_and_close_passes_through():
    with pytest.raises(ValueError, match=r"RealtimeConfig\.speed must be positive"):
        RealtimeConfig(speed=0.0)
    with pytest.raises(ValueError, match=r"RealtimeConfig\.drop_late_s must be >= 0"):
        RealtimeConfig(drop_late_s=-1.0)
    inner = ListSource(_frames([0.0]))
    with RealtimeSource(inner, clock=FakeClock()):
        pass
    assert inner.closed
