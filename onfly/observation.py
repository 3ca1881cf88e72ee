"""The observation: one timestamped RGB-D frame with its pose and camera.

Every source yields these: the embedded world, log and TUM/bag readers, the onboard camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planning.camera import PinholeCamera
from planning.frames import T_BODY_CAM, check_transform, invert_transform, yaw_from_matrix

__all__ = ["Observation"]


@dataclass(frozen=True, eq=False)
class Observation:
    """One RGB-D frame.

    Attributes
    ----------
    t_s : float, seconds on the pilot's clock (or the log's clock)
    rgb : uint8 array (H, W, 3)
    depth_m : float32 array (H, W), z-depth in metres; 0 / NaN / inf / negative mean no reading.
        Checked by :meth:`PinholeCamera.check_depth`: a float dtype (an integer frame is raw
        counts: convert with :func:`planning.camera.depth_from_counts`), not mostly beyond
        65.5 m (millimetres given as metres)
    T_world_cam : array (4, 4), camera optical frame -> world (ENU for the drone)
    camera : PinholeCamera with ``shape == depth_m.shape``
    frame_id : str, unique per frame (the vision-feature cache keys on it)
    T_body_cam : array (4, 4), camera mount on the body (default: forward, level)
    annotation : optional per-frame ground truth the embedded world attaches
        (``vlm.types.FrameAnnotation``); read only by the simulated VLM and by logs
    """

    t_s: float
    rgb: np.ndarray
    depth_m: np.ndarray
    T_world_cam: np.ndarray
    camera: PinholeCamera
    frame_id: str
    T_body_cam: np.ndarray = field(default_factory=T_BODY_CAM.copy)
    annotation: object | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.t_s):
            raise ValueError(f"t_s must be finite, got {self.t_s}")
        rgb = np.asarray(self.rgb)
        self.camera.check_image(rgb, "rgb")
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
        depth = self.camera.check_depth(self.depth_m, "depth_m")  # float metres; counts are refused
        object.__setattr__(self, "depth_m", depth)
        object.__setattr__(self, "T_world_cam", check_transform(self.T_world_cam, "T_world_cam"))
        object.__setattr__(self, "T_body_cam", check_transform(self.T_body_cam, "T_body_cam"))

    @property
    def T_world_body(self) -> np.ndarray:
        """Body pose, shape (4, 4)."""
        return self.T_world_cam @ invert_transform(self.T_body_cam)

    @property
    def position(self) -> np.ndarray:
        """Body position, shape (3,), metres, world frame."""
        return self.T_world_body[:3, 3].copy()

    @property
    def yaw(self) -> float:
        """Body heading in radians."""
        return yaw_from_matrix(self.T_world_body[:3, :3])
