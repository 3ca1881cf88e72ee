"""Pinhole camera model in the optical frame (x right, y down, z forward).

Pixel coordinates ``(u, v)`` are continuous with the centre of pixel ``(col, row)`` at
``(col, row)``: integer coordinates name pixel centres, as in OpenCV. Depth is z-depth in
metres (distance along the optical axis, not ray length).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PinholeCamera", "CameraError", "depth_from_counts", "DEPTH_COUNTS_SATURATED", "DEPTH_IMPLAUSIBLE_M"]


class CameraError(ValueError):
    """Invalid intrinsics or arrays of the wrong shape for this camera."""


#: The largest 16-bit depth count: the encoding's ceiling, not a measurement (no reading).
DEPTH_COUNTS_SATURATED = 65535

#: Farther than any 16-bit millimetre depth image can say (65535 mm, REP 118's ``16UC1``) and
#: than the RGB-D cameras this toolkit reads (D435: 10 m, Kinect: ~10 m). A metres frame whose
#: readings are mostly beyond it was given in millimetres (or another wrong scale).
DEPTH_IMPLAUSIBLE_M = 65.535


def depth_from_counts(counts, counts_per_m: float) -> np.ndarray:
    """Raw 16-bit depth counts -> float32 z-depth in metres, the one conversion every reader uses.

    ``depth_m = counts / counts_per_m``: 5000 per metre for TUM RGB-D PNGs (TUM's "file
    formats" page), 1000 (millimetres) for ROS ``16UC1`` images (REP 118) and a RealSense's
    z16 stream at the D400's default depth unit of 1 mm (librealsense ``get_depth_scale``).
    Count 0 is *no reading* in all three conventions (TUM: "a pixel value of 0 means missing
    value/no data"; librealsense and REP 118 alike) and stays 0. Count 65535, the encoding's
    ceiling, is a saturated or invalid value (OpenNI/Kinect drivers report it for pixels they
    cannot measure; no D435 or Kinect reads 65 m), so it is no reading too (0), never a far
    reading that would clear free space along its ray.

    Raises
    ------
    CameraError
        ``counts`` not an unsigned or signed integer array (a float frame is already metres:
        dividing it again would be a unit mistake), or ``counts_per_m`` not finite and > 0.
    """
    counts = np.asarray(counts)
    if not np.issubdtype(counts.dtype, np.integer):
        raise CameraError(f"depth counts must be an integer array (16-bit sensor counts), got {counts.dtype}")
    scale = float(counts_per_m)
    if not (np.isfinite(scale) and scale > 0):
        raise CameraError(f"depth counts per metre must be finite and > 0, got {counts_per_m}")
    depth = counts.astype(np.float32) / np.float32(scale)
    bad = (counts < 0) | (counts >= DEPTH_COUNTS_SATURATED)
    if bad.any():
        depth[bad] = 0.0
    return depth


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics of an undistorted image.

    Attributes
    ----------
    width, height : int, pixels
    fx, fy : float, focal lengths in pixels
    cx, cy : float, principal point in pixels
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise CameraError(f"image size must be positive, got {self.width} x {self.height}")
        vals = np.array([self.fx, self.fy, self.cx, self.cy], dtype=float)
        if not np.all(np.isfinite(vals)):
            raise CameraError(f"intrinsics must be finite, got fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        # The principal point lies on the image (pixel-centre extents, +- 0.5 px): an RGB-D
        # camera's optical axis meets its own sensor. Outside it, the intrinsics belong to
        # another resolution (a 640 x 480 calibration on a 320 x 240 image) or are swapped.
        if not (-0.5 <= self.cx <= int(self.width) - 0.5 and -0.5 <= self.cy <= int(self.height) - 0.5):
            raise CameraError(
                f"principal point ({self.cx}, {self.cy}) lies outside the {int(self.width)} x {int(self.height)} image "
                "(intrinsics of another resolution?)"
            )
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float = 90.0, vfov_deg: float | None = 60.0) -> "PinholeCamera":
        """Camera with the given full fields of view (the paper's camera: 90 x 60 deg).

        The principal point is the image centre ``((w - 1) / 2, (h - 1) / 2)``. With
        ``vfov_deg=None`` pixels are square (``fy = fx``).
        """
        if not (0.0 < hfov_deg < 180.0):
            raise CameraError(f"hfov_deg must be in (0, 180), got {hfov_deg}")
        fx = (width / 2.0) / np.tan(np.deg2rad(hfov_deg) / 2.0)
        if vfov_deg is None:
            fy = fx
        else:
            if not (0.0 < vfov_deg < 180.0):
                raise CameraError(f"vfov_deg must be in (0, 180), got {vfov_deg}")
            fy = (height / 2.0) / np.tan(np.deg2rad(vfov_deg) / 2.0)
        return cls(width, height, float(fx), float(fy), (width - 1) / 2.0, (height - 1) / 2.0)

    @classmethod
    def from_matrix(cls, K, width: int, height: int) -> "PinholeCamera":
        """Camera from a 3x3 intrinsic matrix."""
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise CameraError(f"K must have shape (3, 3), got {K.shape}")
        return cls(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])

    # -- properties -------------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix, shape (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def K_inv(self) -> np.ndarray:
        """Inverse intrinsic matrix, shape (3, 3)."""
        return np.array(
            [[1.0 / self.fx, 0.0, -self.cx / self.fx], [0.0, 1.0 / self.fy, -self.cy / self.fy], [0.0, 0.0, 1.0]]
        )

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(height, width)`` as numpy orders it."""
        return (self.height, self.width)

    @property
    def hfov_rad(self) -> float:
        """Full horizontal field of view in radians (edge to edge of the image)."""
        return float(2.0 * np.arctan((self.width / 2.0) / self.fx))

    @property
    def vfov_rad(self) -> float:
        """Full vertical field of view in radians."""
        return float(2.0 * np.arctan((self.height / 2.0) / self.fy))

    def scaled(self, factor: float) -> "PinholeCamera":
        """The same camera at a resolution scaled by ``factor`` (pixel-centre convention kept)."""
        w = int(round(self.width * factor))
        h = int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return PinholeCamera(w, h, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5)

    # -- geometry ---------------------------------------------------------------------------
    def project(self, P_cam) -> tuple[np.ndarray, np.ndarray]:
        """Project points to pixels.

        Parameters
        ----------
        P_cam : array, shape (n, 3) or (3,), metres, camera optical frame

        Returns
        -------
        uv : array, shape (n, 2) or (2,), pixels ``(u, v)``; NaN for points with z <= 0
        in_front : bool array, shape (n,) or scalar, True where z > 0
        """
        P = np.asarray(P_cam, dtype=float)
        single = P.ndim == 1
        P = np.atleast_2d(P)
        if P.shape[-1] != 3 or P.ndim != 2:
            raise CameraError(f"P_cam must have shape (n, 3), got {np.shape(P_cam)}")
        z = P[:, 2]
        in_front = z > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(in_front, self.fx * P[:, 0] / z + self.cx, np.nan)
            v = np.where(in_front, self.fy * P[:, 1] / z + self.cy, np.nan)
        uv = np.stack([u, v], axis=-1)
        if single:
            return uv[0], bool(in_front[0])
        return uv, in_front

    def in_image(self, uv, margin_px: float = 0.0) -> np.ndarray:
        """True where ``uv`` (n, 2) lies within the image (pixel-centre extents, ± 0.5 px)."""
        uv = np.asarray(uv, dtype=float)
        u, v = uv[..., 0], uv[..., 1]
        with np.errstate(invalid="ignore"):
            return (
                np.isfinite(u)
                & np.isfinite(v)
                & (u >= -0.5 + margin_px)
                & (u < self.width - 0.5 - margin_px)
                & (v >= -0.5 + margin_px)
                & (v < self.height - 0.5 - margin_px)
            )

    def back_project(self, uv, depth) -> np.ndarray:
        """Lift pixels with z-depth to 3D points.

        Parameters
        ----------
        uv : array, shape (n, 2) or (2,), pixels
        depth : array, shape (n,) or scalar, z-depth in metres

        Returns
        -------
        P_cam : array, shape (n, 3) or (3,), metres, camera optical frame
        """
        uv = np.asarray(uv, dtype=float)
        d = np.asarray(depth, dtype=float)
        single = uv.ndim == 1
        uv2 = np.atleast_2d(uv)
        if uv2.shape[-1] != 2 or uv2.ndim != 2:
            raise CameraError(f"uv must have shape (n, 2), got {uv.shape}")
        d = np.broadcast_to(d, uv2.shape[:1])
        x = (uv2[:, 0] - self.cx) / self.fx * d
        y = (uv2[:, 1] - self.cy) / self.fy * d
        P = np.stack([x, y, d], axis=-1)
        return P[0] if single else P

    def rays(self, normalize: bool = False) -> np.ndarray:
        """Per-pixel ray directions, shape (height, width, 3), optical frame.

        With ``normalize=False`` each ray has z = 1, so ``depth[..., None] * rays`` is the
        back-projected point cloud; with ``normalize=True`` rays are unit vectors (ray length
        ``r`` relates to z-depth by ``z = r * ray_z``).
        """
        u, v = np.meshgrid(np.arange(self.width, dtype=float), np.arange(self.height, dtype=float))
        d = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)
        if normalize:
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d

    def depth_to_points(self, depth, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Back-project a depth image, dropping pixels with no reading (0, NaN, inf, < 0).

        Parameters
        ----------
        depth : array, shape (height, width), z-depth in metres
        stride : keep every ``stride``-th row and column

        Returns
        -------
        P_cam : array, shape (n, 3), metres, optical frame
        valid : bool array, shape (height // stride, width // stride)-ish mask of kept pixels
        """
        depth = self.check_image(depth, "depth")
        d = depth[::stride, ::stride].astype(float)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d) & (d > 0)
        rays = self.rays()[::stride, ::stride]
        P = rays[valid] * d[valid][:, None]
        return P, valid

    def check_depth(self, depth, name: str = "depth_m") -> np.ndarray:
        """Check a z-depth image in metres for this camera; return it as float32 (H, W).

        The one depth-validation rule of the toolkit (Observation, ``EsdfMap.integrate`` and
        the verifier's ``CandidateGoal`` call it):

        - shape ``(height, width)``, 2-D;
        - a floating dtype. An integer frame (``uint16``) is raw sensor counts, not metres:
          a 1.5 m wall in millimetres would read 1500 m, beyond range, and clear free space
          through the wall. Convert with :func:`depth_from_counts` and the source's scale;
        - not mostly beyond :data:`DEPTH_IMPLAUSIBLE_M`: a float frame in millimetres (REP 118
          says ``32FC1`` is metres) has its readings 1000 times too far and the same effect;
          a few far or garbage readings (1e6 m) are readings beyond the map's range and are
          kept (they clear at most ``max_range_m``, as the map documents).

        Values 0, NaN, +-inf and negatives are *no reading* (RealSense, TUM and REP 118 give 0;
        ZED gives NaN / inf) and are left as they are: every consumer drops them.

        Raises
        ------
        CameraError
            Naming the array, with what is wrong and the conversion to use.
        """
        arr = np.asarray(depth)
        if arr.ndim != 2:
            raise CameraError(f"{name} must be a 2-D ({self.height}, {self.width}) depth image, got shape {arr.shape}")
        self.check_image(arr, name)
        if np.issubdtype(arr.dtype, np.integer) or arr.dtype == np.bool_:
            raise CameraError(
                f"{name} is {arr.dtype}: raw sensor counts, not metres; convert with "
                "planning.camera.depth_from_counts(counts, counts_per_m) (1000 for millimetres, 5000 for TUM)"
            )
        if not np.issubdtype(arr.dtype, np.floating):
            raise CameraError(f"{name} must be a float z-depth image in metres, got dtype {arr.dtype}")
        d = arr if arr.dtype == np.float32 else arr.astype(np.float32)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d) & (d > 0)
            n_valid = int(np.count_nonzero(valid))
            n_far = int(np.count_nonzero(valid & (d > np.float32(DEPTH_IMPLAUSIBLE_M))))
        if n_valid and 2 * n_far > n_valid:
            raise CameraError(
                f"{name}: {n_far} of {n_valid} readings lie beyond {DEPTH_IMPLAUSIBLE_M} m (median "
                f"{float(np.median(d[valid])):.4g}); depth must be metres, was it given in millimetres?"
            )
        return d

    def check_image(self, image, name: str = "image") -> np.ndarray:
        """Check that an image's first two dimensions match ``(height, width)``."""
        image = np.asarray(image)
        if image.ndim < 2 or image.shape[:2] != (self.height, self.width):
            raise CameraError(f"{name} must have shape ({self.height}, {self.width}[, ...]), got {image.shape}")
        return image
