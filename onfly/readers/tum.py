"""Reader of TUM RGB-D folders.

A folder holds ``rgb.txt`` and ``depth.txt`` (lines ``timestamp filename``),
``groundtruth.txt`` (lines ``timestamp tx ty tz qx qy qz qw``: the camera pose, camera optical
frame -> world, metres, scalar-last quaternion), the images those files name (colour images
of any format OpenCV reads; depth as 16-bit PNG, ``depth_m = value / depth_scale`` with scale
5000 by default, 0 = no reading, 65535 = saturated, no reading: :func:`planning.camera.depth_from_counts`), and optionally ``intrinsics.txt`` holding ``fx fy cx cy``
(pixels) on its first non-comment line. Lines starting with ``#`` and blank lines are
ignored; fields may be separated by spaces, tabs or commas, as TUM's tools accept.

Each depth frame becomes one :class:`Observation` at the depth timestamp:

- the colour frame is associated by nearest timestamp within ``max_difference_s``
  (greedy, each frame used once, as TUM's ``associate.py``; default 0.02 s);
- the pose is interpolated at the depth timestamp (linear position, slerp rotation) between
  the ground-truth samples around it; depth frames whose bracketing samples are more than
  ``pose_max_gap_s`` apart, or that lie outside the ground truth by more than
  ``max_difference_s``, are dropped (counted and logged);
- intrinsics come from ``TumConfig.intrinsics`` if given, else ``intrinsics.txt``, else
  :data:`TUM_DEFAULT_INTRINSICS` (a warning is logged).

Observation.T_world_cam is the ground-truth pose itself (TUM poses are camera poses);
T_body_cam is ``TumConfig.T_body_cam`` (default: the forward, level mount).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from onfly.observation import Observation
from onfly.readers.poses import PoseTrack, associate
from planning.camera import CameraError, PinholeCamera, depth_from_counts
from planning.frames import T_BODY_CAM, check_transform, quat_wxyz_from_xyzw

__all__ = ["TumFormatError", "TumConfig", "TumReader", "TUM_DEFAULT_INTRINSICS", "is_tum_dir", "parse_intrinsics"]

log = logging.getLogger(__name__)

#: ``(fx, fy, cx, cy)`` in pixels used when neither the config nor ``intrinsics.txt`` gives
#: intrinsics: the "ROS default" calibration TUM publishes for its 640x480 Kinect data.
TUM_DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5)

RGB_LIST = "rgb.txt"
DEPTH_LIST = "depth.txt"
GROUNDTRUTH = "groundtruth.txt"
INTRINSICS = "intrinsics.txt"


class TumFormatError(ValueError):
    """A missing or malformed part of a TUM folder; the message names the file (and line)."""


def parse_intrinsics(text: str) -> tuple[float, float, float, float]:
    """``fx,fy,cx,cy`` (commas or spaces) -> a tuple of four floats, or ValueError."""
    parts = text.replace(",", " ").split()
    if len(parts) != 4:
        raise ValueError(f"intrinsics must be four numbers fx fy cx cy, got {text!r}")
    return tuple(float(p) for p in parts)  # type: ignore[return-value]


def _default_mount() -> np.ndarray:
    return T_BODY_CAM.copy()


@dataclass(frozen=True, eq=False)
class TumConfig:
    """Options of :class:`TumReader`.

    Attributes
    ----------
    depth_scale : depth PNG value per metre (TUM: 5000)
    max_difference_s : association tolerance between depth, colour and pose times, seconds
    pose_max_gap_s : largest gap between ground-truth samples to interpolate across, seconds
    intrinsics : ``(fx, fy, cx, cy)`` in pixels overriding ``intrinsics.txt``, or None
    T_body_cam : (4, 4) camera mount given to every observation
    """

    depth_scale: float = 5000.0
    max_difference_s: float = 0.02
    pose_max_gap_s: float = 0.5
    intrinsics: tuple[float, float, float, float] | None = None
    T_body_cam: np.ndarray = field(default_factory=_default_mount)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise ValueError(f"TumConfig.depth_scale must be positive, got {self.depth_scale}")
        if not (np.isfinite(self.max_difference_s) and self.max_difference_s > 0):
            raise ValueError(f"TumConfig.max_difference_s must be positive, got {self.max_difference_s}")
        if not (self.pose_max_gap_s > 0):
            raise ValueError(f"TumConfig.pose_max_gap_s must be positive, got {self.pose_max_gap_s}")
        if self.intrinsics is not None:
            k = tuple(float(v) for v in self.intrinsics)
            if len(k) != 4:
                raise ValueError(f"TumConfig.intrinsics must be (fx, fy, cx, cy), got {self.intrinsics}")
            object.__setattr__(self, "intrinsics", k)
        object.__setattr__(self, "T_body_cam", check_transform(self.T_body_cam, "TumConfig.T_body_cam"))


def is_tum_dir(path: Path) -> bool:
    """True if ``path`` is a directory holding ``rgb.txt`` and ``depth.txt``."""
    path = Path(path)
    return path.is_dir() and (path / RGB_LIST).is_file() and (path / DEPTH_LIST).is_file()


def _data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TumFormatError(f"{path}: missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TumFormatError(f"{path}: cannot read ({exc})") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        yield lineno, s.replace(",", " ").replace("\t", " ").split()


def _read_file_list(path: Path) -> tuple[np.ndarray, list[str], list[int]]:
    times, names, lines = [], [], []
    for lineno, fields in _data_lines(path):
        if len(fields) != 2:
            raise TumFormatError(f"{path}:{lineno}: expected 'timestamp filename', got {len(fields)} fields")
        try:
            t = float(fields[0])
        except ValueError:
            raise TumFormatError(f"{path}:{lineno}: timestamp {fields[0]!r} is not a number") from None
        if not np.isfinite(t):
            raise TumFormatError(f"{path}:{lineno}: timestamp {fields[0]!r} is not finite")
        times.append(t)
        names.append(fields[1])
        lines.append(lineno)
    if not times:
        raise TumFormatError(f"{path}: no entries")
    return np.array(times), names, lines


def _read_groundtruth(path: Path) -> PoseTrack:
    rows = []
    for lineno, fields in _data_lines(path):
        if len(fields) != 8:
            raise TumFormatError(f"{path}:{lineno}: expected 't tx ty tz qx qy qz qw', got {len(fields)} fields")
        try:
            vals = [float(f) for f in fields]
        except ValueError:
            raise TumFormatError(f"{path}:{lineno}: not all fields are numbers") from None
        if not np.all(np.isfinite(vals)):
            raise TumFormatError(f"{path}:{lineno}: non-finite value")
        if np.linalg.norm(vals[4:8]) < 1e-6:
            raise TumFormatError(f"{path}:{lineno}: zero quaternion")
        rows.append(vals)
    if not rows:
        raise TumFormatError(f"{path}: no poses")
    a = np.array(rows)
    return PoseTrack.from_samples(a[:, 0], a[:, 1:4], quat_wxyz_from_xyzw(a[:, 4:8]))


@dataclass(frozen=True)
class _Frame:
    t_s: float
    depth_path: Path
    rgb_path: Path
    T_world_cam: np.ndarray


class TumReader:
    """Observations of a TUM RGB-D folder, one per associated depth frame.

    Parameters
    ----------
    path : the folder
    config : :class:`TumConfig`

    Everything but the images is parsed and checked at construction (lists, poses,
    intrinsics, existence of every image file used), so a broken folder fails before the
    first frame. Images are read while iterating.

    Attributes
    ----------
    poses : PoseTrack of ``groundtruth.txt``
    camera : PinholeCamera (size from the first depth image)
    dropped : dict of how many depth frames were dropped and why
    """

    kind = "tum"

    def __init__(self, path, config: TumConfig = TumConfig()) -> None:
        self.path = Path(path)
        self.config = config
        if not self.path.is_dir():
            raise TumFormatError(f"{self.path}: not a directory (a TUM folder holds {RGB_LIST}, {DEPTH_LIST}, {GROUNDTRUTH})")
        t_rgb, rgb_names, rgb_lines = _read_file_list(self.path / RGB_LIST)
        t_depth, depth_names, depth_lines = _read_file_list(self.path / DEPTH_LIST)
        self.poses = _read_groundtruth(self.path / GROUNDTRUTH)
        intrinsics = self._intrinsics()

        tol = config.max_difference_s
        frames: list[_Frame] = []
        self.dropped = {"no_rgb": 0, "no_pose": 0}
        matched_rgb = dict(associate(t_depth, t_rgb, tol))
        self.dropped["no_rgb"] = len(t_depth) - len(matched_rgb)
        for i in sorted(matched_rgb, key=lambda i: (t_depth[i], i)):
            T = self.poses.interpolate(float(t_depth[i]), max_gap_s=config.pose_max_gap_s, end_tolerance_s=tol)
            if T is None:
                self.dropped["no_pose"] += 1
                continue
            depth_path = self.path / depth_names[i]
            rgb_path = self.path / rgb_names[matched_rgb[i]]
            if not depth_path.is_file():
                raise TumFormatError(f"{depth_path}: missing (named on {self.path / DEPTH_LIST}:{depth_lines[i]})")
            if not rgb_path.is_file():
                raise TumFormatError(f"{rgb_path}: missing (named on {self.path / RGB_LIST}:{rgb_lines[matched_rgb[i]]})")
            frames.append(_Frame(float(t_depth[i]), depth_path, rgb_path, T))
        if any(self.dropped.values()):
            log.warning("%s: dropped depth frames: %s", self.path, self.dropped)
        if not frames:
            raise TumFormatError(
                f"{self.path}: no depth frame has both a colour frame within {tol} s and a ground-truth pose "
                f"(depth {len(t_depth)}, rgb {len(t_rgb)}, poses {len(self.poses)})"
            )
        self._frames = frames
        h, w = self._read_depth_png(frames[0].depth_path).shape
        fx, fy, cx, cy = intrinsics
        try:
            self.camera = PinholeCamera(w, h, fx, fy, cx, cy)
        except CameraError as exc:  # fx <= 0, a principal point off this image: fail before the first frame
            raise TumFormatError(f"{self.path}: intrinsics {intrinsics} ({self._intrinsics_origin()}) do not fit its {w} x {h} depth images: {exc}") from None

    def _intrinsics_origin(self) -> str:
        if self.config.intrinsics is not None:
            return "TumConfig.intrinsics"
        return str(self.path / INTRINSICS) if (self.path / INTRINSICS).is_file() else "TUM's default"

    def _intrinsics(self) -> tuple[float, float, float, float]:
        if self.config.intrinsics is not None:
            return self.config.intrinsics
        path = self.path / INTRINSICS
        if path.is_file():
            for lineno, fields in _data_lines(path):
                try:
                    return parse_intrinsics(" ".join(fields))
                except ValueError:
                    raise TumFormatError(f"{path}:{lineno}: expected four numbers 'fx fy cx cy'") from None
            raise TumFormatError(f"{path}: no 'fx fy cx cy' line")
        log.warning("%s: no %s and no intrinsics option; using TUM's default %s", self.path, INTRINSICS, TUM_DEFAULT_INTRINSICS)
        return TUM_DEFAULT_INTRINSICS

    # -- protocol --------------------------------------------------------------------------------
    def __enter__(self) -> "TumReader":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def close(self) -> None:
        """No file stays open between frames."""

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def timestamps_s(self) -> np.ndarray:
        """Depth timestamps of the frames this reader yields, shape (n,), seconds."""
        return np.array([f.t_s for f in self._frames])

    def __iter__(self) -> Iterator[Observation]:
        for frame in self._frames:
            yield self._load(frame)

    # -- images ----------------------------------------------------------------------------------
    @staticmethod
    def _read_depth_png(path: Path) -> np.ndarray:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise TumFormatError(f"{path}: cannot read depth image")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise TumFormatError(f"{path}: depth must be a 16-bit single-channel PNG, got {raw.dtype} {raw.shape}")
        return raw

    def _load(self, frame: _Frame) -> Observation:
        raw = self._read_depth_png(frame.depth_path)
        depth_m = depth_from_counts(raw, self.config.depth_scale)  # 0 and 65535: no reading
        bgr = cv2.imread(str(frame.rgb_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise TumFormatError(f"{frame.rgb_path}: cannot read colour image")
        rgb = np.ascontiguousarray(bgr[:, :, ::-1])
        if rgb.shape[:2] != depth_m.shape or depth_m.shape != self.camera.shape:
            raise TumFormatError(
                f"{frame.rgb_path}: colour {rgb.shape[:2]} and depth {depth_m.shape} ({frame.depth_path.name}) "
                f"sizes differ from the camera {self.camera.shape}"
            )
        return Observation(
            t_s=frame.t_s,
            rgb=rgb,
            depth_m=depth_m,
            T_world_cam=frame.T_world_cam,
            camera=self.camera,
            frame_id=f"tum:{self.path.name}:{frame.depth_path.relative_to(self.path)}",
            T_body_cam=self.config.T_body_cam,
        )
