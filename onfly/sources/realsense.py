"""Intel RealSense RGB-D camera as an observation source (optional extra).

``pip install onfly[realsense]`` installs ``pyrealsense2``; it is imported only when a
:class:`RealSenseSource` is iterated, so the rest of OnFly never needs it. Without it the
source raises :class:`RealSenseUnavailableError` naming the extra.

Streams: colour ``rgb8`` and depth ``z16`` at the same resolution and rate, depth aligned to
colour (``rs.align(rs.stream.color)``), so one :class:`~planning.camera.PinholeCamera` (the
colour intrinsics) serves both images. Depth is converted to float32 metres along the optical
axis with the device's depth unit (D435: 1 mm); 0 stays 0 (no reading), and so does 65535
(saturated: :func:`planning.camera.depth_from_counts`).

A RealSense knows no pose. Each frame is placed with the vehicle pose at arrival, from
``pose_source() -> T_world_body (4, 4)`` (the MAVLink bridge's state), and the camera mount
``T_body_cam``; frames that arrive while no pose is known are skipped.

Defaults are the published D435 colour calibration at 640 x 480 (``../shared/realdata``):
fx 617.2, fy 617.4, cx 324.6, cy 242.5, depth unit 1 mm. With ``use_device_intrinsics``
(default) the calibration the device reports replaces them.

Not tested against hardware here (no camera on the build machines): the conversion
(:func:`observation_from_realsense`) and the missing-extra error are tested; the pyrealsense2
calls follow librealsense's documented Python API.
"""

from __future__ import annotations

import importlib
import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import numpy as np

from onfly.observation import Observation
from planning.camera import PinholeCamera, depth_from_counts
from planning.frames import T_BODY_CAM, check_transform

__all__ = [
    "RealSenseUnavailableError",
    "RealSenseConfig",
    "RealSenseSource",
    "D435_COLOR_640x480",
    "import_pyrealsense2",
    "observation_from_realsense",
]

log = logging.getLogger(__name__)

#: Published D435 colour intrinsics at 640 x 480: (width, height, fx, fy, cx, cy), pixels.
D435_COLOR_640x480 = (640, 480, 617.2, 617.4, 324.6, 242.5)


class RealSenseUnavailableError(ImportError):
    """pyrealsense2 is not installed (the ``realsense`` extra)."""


def import_pyrealsense2() -> Any:
    """The ``pyrealsense2`` module, or :class:`RealSenseUnavailableError` telling how to get it."""
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as exc:
        raise RealSenseUnavailableError(
            "the RealSense camera needs pyrealsense2, an optional extra: pip install onfly[realsense] "
            f"(import failed: {exc})"
        ) from exc


@dataclass(frozen=True)
class RealSenseConfig:
    """Streams and calibration of the RealSense.

    Attributes
    ----------
    width, height : pixels of both streams
    fps : frames per second of both streams
    fx, fy, cx, cy : colour intrinsics, pixels (used unless ``use_device_intrinsics``)
    depth_unit_m : metres per depth count (used unless ``use_device_intrinsics``)
    use_device_intrinsics : take intrinsics and depth unit from the device
    serial : serial number of the device to open (None: the first one)
    wait_timeout_ms : a frameset not delivered within this raises TimeoutError (read again)
    T_body_cam : (4, 4) camera mount on the body (default forward and level)
    """

    width: int = D435_COLOR_640x480[0]
    height: int = D435_COLOR_640x480[1]
    fps: int = 30
    fx: float = D435_COLOR_640x480[2]
    fy: float = D435_COLOR_640x480[3]
    cx: float = D435_COLOR_640x480[4]
    cy: float = D435_COLOR_640x480[5]
    depth_unit_m: float = 0.001
    use_device_intrinsics: bool = True
    serial: str | None = None
    wait_timeout_ms: int = 1000
    T_body_cam: np.ndarray = field(default_factory=T_BODY_CAM.copy)

    def __post_init__(self) -> None:
        for name in ("width", "height", "fps", "wait_timeout_ms"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v > 0):
                raise ValueError(f"RealSenseConfig.{name} must be a positive integer, got {v!r}")
        for name in ("fx", "fy", "cx", "cy", "depth_unit_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"RealSenseConfig.{name} must be positive and finite, got {v!r}")
        object.__setattr__(self, "T_body_cam", check_transform(self.T_body_cam, "RealSenseConfig.T_body_cam"))

    @property
    def camera(self) -> PinholeCamera:
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy)


def observation_from_realsense(
    color_rgb: np.ndarray,
    depth_counts: np.ndarray,
    depth_unit_m: float,
    camera: PinholeCamera,
    T_world_body: np.ndarray,
    t_s: float,
    frame_id: str,
    T_body_cam: np.ndarray = T_BODY_CAM,
) -> Observation:
    """One aligned RealSense frame pair as an :class:`Observation`.

    Parameters
    ----------
    color_rgb : uint8 (H, W, 3), RGB order
    depth_counts : uint16 (H, W), depth aligned to colour, in device units (0 = no reading)
    depth_unit_m : metres per count (D435: 0.001)
    camera : colour intrinsics, ``camera.shape == (H, W)``
    T_world_body : (4, 4) vehicle pose at capture, world ENU
    t_s : capture time on the pilot's clock, seconds
    frame_id : unique id
    T_body_cam : (4, 4) camera mount

    Returns an Observation with float32 z-depth in metres and ``T_world_cam = T_world_body @
    T_body_cam``. Raises ValueError on mismatched shapes or types.
    """
    depth_counts = np.asarray(depth_counts)
    if depth_counts.dtype != np.uint16:
        raise ValueError(f"depth_counts must be uint16 (z16), got {depth_counts.dtype}")
    if not (np.isfinite(depth_unit_m) and depth_unit_m > 0):
        raise ValueError(f"depth_unit_m must be positive, got {depth_unit_m}")
    depth_m = depth_from_counts(depth_counts, 1.0 / depth_unit_m)  # 0 and 65535: no reading
    T_world_body = check_transform(T_world_body, "T_world_body")
    T_body_cam = check_transform(T_body_cam, "T_body_cam")
    return Observation(
        t_s=float(t_s),
        rgb=np.ascontiguousarray(color_rgb),
        depth_m=depth_m,
        T_world_cam=T_world_body @ T_body_cam,
        camera=camera,
        frame_id=frame_id,
        T_body_cam=T_body_cam,
    )


class RealSenseSource:
    """Iterable of observations from a RealSense (see the module docstring).

    Parameters
    ----------
    config : RealSenseConfig
    pose_source : ``() -> T_world_body (4, 4)`` or None when no pose is known yet
    clock : the pilot's clock (seconds) stamping each frame at arrival
    """

    kind = "realsense"
    path = None

    def __init__(self, config: RealSenseConfig, pose_source: Callable[[], np.ndarray | None], clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.pose_source = pose_source
        self.clock = clock
        self.skipped_no_pose = 0
        self._pipeline = None

    def close(self) -> None:
        pipeline, self._pipeline = self._pipeline, None
        if pipeline is not None:
            pipeline.stop()

    def __enter__(self) -> "RealSenseSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _start(self, rs):
        c = self.config
        rs_config = rs.config()
        if c.serial is not None:
            rs_config.enable_device(c.serial)
        rs_config.enable_stream(rs.stream.color, c.width, c.height, rs.format.rgb8, c.fps)
        rs_config.enable_stream(rs.stream.depth, c.width, c.height, rs.format.z16, c.fps)
        pipeline = rs.pipeline()
        profile = pipeline.start(rs_config)
        self._pipeline = pipeline
        camera, unit = c.camera, c.depth_unit_m
        if c.use_device_intrinsics:
            intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
            camera = PinholeCamera(int(intr.width), int(intr.height), float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy))
            unit = float(profile.get_device().first_depth_sensor().get_depth_scale())
        log.info("RealSense started: %dx%d @ %d Hz, fx %.1f fy %.1f cx %.1f cy %.1f, depth unit %.4g m",
                 camera.width, camera.height, c.fps, camera.fx, camera.fy, camera.cx, camera.cy, unit)
        return pipeline, rs.align(rs.stream.color), camera, unit

    def __iter__(self) -> Iterator[Observation]:
        rs = import_pyrealsense2()
        pipeline, align, camera, unit = self._start(rs)
        try:
            while self._pipeline is not None:
                try:
                    frames = pipeline.wait_for_frames(self.config.wait_timeout_ms)
                except RuntimeError as exc:  # librealsense reports a timeout as RuntimeError
                    raise TimeoutError(f"no RealSense frameset within {self.config.wait_timeout_ms} ms: {exc}") from exc
                aligned = align.process(frames)
                color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
                if not color or not depth:
                    continue
                T_world_body = self.pose_source()
                if T_world_body is None:
                    self.skipped_no_pose += 1
                    continue
                yield observation_from_realsense(
                    np.asanyarray(color.get_data()),
                    np.asanyarray(depth.get_data()),
                    unit,
                    camera,
                    T_world_body,
                    self.clock(),
                    f"realsense/{int(color.get_frame_number()):08d}",
                    self.config.T_body_cam,
                )
        finally:
            self.close()
