"""Onboard camera sources: the newest-frame feed, polled renderers, recordings at real time,
camera specs, and the RealSense source (conversion, a fake pyrealsense2 module, the missing
extra). No RealSense hardware here: the pyrealsense2 calls are checked against a fake of its
documented API only."""

import queue
import sys
import threading
import types

import numpy as np
import pytest

from onfly.observation import Observation
from onfly.readers.tum import TumReader
from onfly.sources.camera import CameraError, CameraFeed, PolledSource, open_camera
from onfly.sources.realsense import (
    D435_COLOR_640x480,
    RealSenseConfig,
    RealSenseSource,
    RealSenseUnavailableError,
    import_pyrealsense2,
    observation_from_realsense,
)
from planning.camera import PinholeCamera
from planning.frames import T_BODY_CAM, body_transform, cam_transform_from_body, transform_points
from realdata_paths import REALDATA

TUM = REALDATA / "7scenes-kitchen-tum"


def frame(i, t_s=None):
    cam = PinholeCamera.from_fov(8, 6, 90, 60)
    return Observation(float(i if t_s is None else t_s), np.full((6, 8, 3), i, np.uint8), np.full((6, 8), 2.0, np.float32),
                       cam_transform_from_body(body_transform([i, 0, 1], 0.0)), cam, f"f{i}")


class QueueSource:
    """A live source the test feeds: yields what is put, raises exceptions put, ends on None."""

    def __init__(self):
        self.q = queue.Queue()
        self.closed = False

    def __iter__(self):
        while True:
            item = self.q.get(timeout=5)
            if item is None:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self):
        self.closed = True


def wait_for(pred, timeout_s=5.0):
    done = threading.Event()
    for _ in range(int(timeout_s / 0.005)):
        if pred():
            return True
        done.wait(0.005)
    return False


class TickClock:
    def __init__(self, t=50.0):
        self.t = t

    def __call__(self):
        return self.t


def test_feed_hands_out_the_newest_frame_once_and_counts_skipped_ones():
    src = QueueSource()
    clock = TickClock(50.0)
    with CameraFeed(src, clock=clock) as feed:
        assert feed.latest() is None and feed.age_s() == float("inf")
        for i in range(3):
            src.q.put(frame(i))
        assert wait_for(lambda: feed.received == 3)
        got = feed.latest()
        assert got.frame_id == "f2" and got.t_s == 50.0  # restamped on the pilot's clock, pose kept
        np.testing.assert_allclose(got.T_world_cam, frame(2).T_world_cam)
        assert feed.latest() is None and feed.skipped == 2 and feed.taken == 1
        clock.t = 50.4
        assert feed.age_s() == pytest.approx(0.4) and feed.peek().frame_id == "f2"
        src.q.put(None)
        assert wait_for(lambda: feed.ended)
    assert src.closed and feed.stats()["ended"] and feed.error is None


def test_feed_retries_timeouts_and_connection_errors_and_stops_on_anything_else():
    src = QueueSource()
    with CameraFeed(src, retry_s=0.01) as feed:
        src.q.put(TimeoutError("no frame"))
        src.q.put(ConnectionError("refused"))
        src.q.put(frame(7))
        assert wait_for(lambda: feed.received == 1)
        assert feed.timeouts == 1 and feed.reconnects == 1 and feed.latest().frame_id == "f7"
        src.q.put("not an observation")
        assert wait_for(lambda: feed.error is not None)
        assert isinstance(feed.error, TypeError) and "yielded str, not an Observation" in str(feed.error)
        assert wait_for(lambda: not feed.running)
    with pytest.raises(ValueError, match="retry_s must be positive"):
        CameraFeed(src, retry_s=0.0)


class StepClock:
    """PlaybackClock that jumps to each requested time (no sleeping)."""

    def __init__(self, t=0.0):
        self.t = t
        self.waits = []

    def now_s(self):
        return self.t

    def sleep_until_s(self, t_s):
        self.waits.append(t_s)
        self.t = max(self.t, t_s)


def test_polled_source_calls_the_renderer_once_per_period_and_skips_none():
    clock = StepClock(10.0)
    calls = []

    def render():
        calls.append(clock.t)
        return None if len(calls) == 2 else frame(len(calls))

    src = PolledSource(render, 0.5, clock)
    it = iter(src)
    got = [next(it).frame_id for _ in range(3)]
    assert got == ["f1", "f3", "f4"] and calls == [10.0, 10.5, 11.0, 11.5]
    src.close()
    assert list(it) == []
    with pytest.raises(ValueError, match="period_s must be positive"):
        PolledSource(render, 0.0)


def test_a_tum_folder_plays_at_real_time_on_the_pilots_clock():
    clock = StepClock(100.0)
    feed = open_camera(str(TUM), clock=clock, speed=2.0)
    reader = TumReader(TUM)
    stamps = [o.t_s for o in reader]
    reader.close()
    with feed:
        assert wait_for(lambda: feed.ended, 20.0)
    assert feed.received == len(stamps) == 60 and feed.error is None
    last = feed.latest()
    # released at start + (t_k - t_0) / speed on the given clock, and stamped with that time
    assert last.t_s == pytest.approx(100.0 + (stamps[-1] - stamps[0]) / 2.0)
    assert clock.waits[-1] == pytest.approx(last.t_s)


def test_camera_specs_that_name_no_source_are_refused():
    with pytest.raises(CameraError, match="tcp://HOST:PORT, 'realsense' or a recording path"):
        open_camera("udp://127.0.0.1:5600")
    with pytest.raises(CameraError, match="camera URL must look like tcp://127.0.0.1:PORT"):
        open_camera("tcp://127.0.0.1")
    with pytest.raises(CameraError, match="no such file or directory"):
        open_camera("/nonexistent/recording")
    with pytest.raises(CameraError, match="needs pose_source"):
        open_camera("realsense")
    with pytest.raises(CameraError, match="camera spec must be"):
        open_camera("  ")


# -- RealSense ----------------------------------------------------------------------------------------
def test_observation_from_realsense_scales_depth_and_places_the_frame_with_the_vehicle_pose():
    cfg = RealSenseConfig()
    cam = cfg.camera
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == D435_COLOR_640x480
    rgb = np.zeros((480, 640, 3), np.uint8)
    depth = np.zeros((480, 640), np.uint16)
    depth[242, 325] = 2000  # 2 m at (about) the principal point
    depth[0, 0] = 65534  # the largest count that is a reading
    depth[0, 1] = 65535  # the 16-bit ceiling: saturated, no reading (planning.camera.depth_from_counts)
    T_world_body = body_transform([1.0, 2.0, 1.5], np.pi / 2)
    obs = observation_from_realsense(rgb, depth, 0.001, cam, T_world_body, 12.5, "rs/1")
    assert obs.depth_m.dtype == np.float32 and obs.depth_m[242, 325] == np.float32(2.0) and obs.depth_m[1, 1] == 0.0
    assert obs.depth_m[0, 0] == pytest.approx(65.534) and obs.depth_m[0, 1] == 0.0
    np.testing.assert_allclose(obs.T_world_cam, T_world_body @ T_BODY_CAM)
    # the principal ray at 2 m lands 2 m ahead of the body: +y in the world for yaw = 90 deg
    p_cam = cam.back_project(np.array([cam.cx, cam.cy]), 2.0)
    np.testing.assert_allclose(transform_points(obs.T_world_cam, p_cam), [1.0, 4.0, 1.5], atol=1e-9)
    with pytest.raises(ValueError, match="depth_counts must be uint16"):
        observation_from_realsense(rgb, depth.astype(np.float32), 0.001, cam, T_world_body, 0.0, "x")
    with pytest.raises(ValueError, match="RealSenseConfig.fx must be positive"):
        RealSenseConfig(fx=0.0)


def test_missing_pyrealsense2_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as if not installed
    with pytest.raises(RealSenseUnavailableError, match=r"pip install onfly\[realsense\]"):
        import_pyrealsense2()
    src = RealSenseSource(RealSenseConfig(), lambda: np.eye(4))
    with pytest.raises(RealSenseUnavailableError, match="optional extra"):
        next(iter(src))


def fake_pyrealsense2(n_frames, intrinsics=(320, 240, 300.0, 301.0, 160.5, 119.5), depth_scale=0.00025):
    """A stand-in for the documented pyrealsense2 API (pipeline, config, align, frames)."""
    rs = types.ModuleType("pyrealsense2")
    rs.stream = types.SimpleNamespace(color="color", depth="depth")
    rs.format = types.SimpleNamespace(rgb8="rgb8", z16="z16")
    calls = []
    w, h = intrinsics[:2]

    class Frame:
        def __init__(self, data, n):
            self.data, self.n = data, n

        def get_data(self):
            return self.data

        def get_frame_number(self):
            return self.n

        def __bool__(self):
            return True

    class Frameset:
        def __init__(self, n):
            self.n = n

        def get_color_frame(self):
            return Frame(np.full((h, w, 3), self.n, np.uint8), self.n)

        def get_depth_frame(self):
            return Frame(np.full((h, w), 4000, np.uint16), self.n)

    class Pipeline:
        def __init__(self):
            self.n = 0
            self.stopped = False

        def start(self, config):
            calls.append(("start", tuple(config.streams)))
            intr = types.SimpleNamespace(width=w, height=h, fx=intrinsics[2], fy=intrinsics[3], ppx=intrinsics[4], ppy=intrinsics[5])
            sensor = types.SimpleNamespace(get_depth_scale=lambda: depth_scale)
            return types.SimpleNamespace(
                get_stream=lambda s: types.SimpleNamespace(as_video_stream_profile=lambda: types.SimpleNamespace(get_intrinsics=lambda: intr)),
                get_device=lambda: types.SimpleNamespace(first_depth_sensor=lambda: sensor),
            )

        def wait_for_frames(self, timeout_ms):
            if self.n >= n_frames:
                raise RuntimeError("Frame didn't arrive within 1000")
            self.n += 1
            return Frameset(self.n)

        def stop(self):
            calls.append(("stop",))

    class Config:
        def __init__(self):
            self.streams = []

        def enable_stream(self, *args):
            self.streams.append(args)

        def enable_device(self, serial):
            calls.append(("device", serial))

    class Align:
        def __init__(self, to):
            calls.append(("align", to))

        def process(self, frames):
            return frames

    rs.pipeline, rs.config, rs.align = Pipeline, Config, Align
    return rs, calls


def test_realsense_source_streams_aligned_frames_with_device_calibration(monkeypatch):
    rs, calls = fake_pyrealsense2(n_frames=3)
    monkeypatch.setitem(sys.modules, "pyrealsense2", rs)
    poses = [None, body_transform([0, 0, 1], 0.0), body_transform([1, 0, 1], 0.0)]
    src = RealSenseSource(RealSenseConfig(serial="123"), lambda: poses.pop(0), clock=lambda: 7.0)
    it = iter(src)
    a, b = next(it), next(it)
    assert src.skipped_no_pose == 1  # the first frameset arrived before any pose
    assert (a.frame_id, b.frame_id) == ("realsense/00000002", "realsense/00000003")
    assert a.camera == PinholeCamera(320, 240, 300.0, 301.0, 160.5, 119.5) and a.t_s == 7.0
    assert a.depth_m[0, 0] == pytest.approx(1.0)  # 4000 counts x 0.25 mm from the device
    np.testing.assert_allclose(b.position, [1, 0, 1])
    with pytest.raises(TimeoutError, match="no RealSense frameset within 1000 ms"):
        next(it)
    assert calls[0] == ("device", "123")
    assert calls[1] == ("start", (("color", 640, 480, "rgb8", 30), ("depth", 640, 480, "z16", 30)))
    assert ("align", "color") in calls and calls[-1] == ("stop",)
