"""Semantic-geometric verifier: from a VLM target pixel to a safe, instruction-consistent goal.

Paper Sec. "Semantic-Geometric Verified Local Planning". Input is a :class:`CandidateGoal`
``G_c = [p_x, p_y, depth_t, f_t, pose_t]``; output is a :class:`VerifiedGoal` with the goal in
the world frame (or an explicit rejection) and a :class:`VerificationRecord` of what was done.

1. **Semantic-guided refinement.** ``d = depth(p)``. If ``d > D_max`` or ``p`` has no reading,
   refinement is skipped (the record says which) and ``p' = p``; the range is then gated to the
   clear part of ``p``'s ray, and an unread pixel is bounded by the surface around its hole (it
   is never open space; see :mod:`planning.verifier_config`). Otherwise the cosine
   similarity of the patch features against the feature at ``p`` is thresholded at ``tau``
   inside a square ROI around ``p``, the 4-connected component containing ``p`` is kept, and
   ``p'`` is the pixel of that component nearest to ``p`` that passes the clearance check under
   the obstacle rule evaluated at ``p'`` itself. Without features (geometric-only mode, flagged
   in the record) the component is the target's *surface*: the pixels depth-continuous with
   ``p`` inside the ROI, bounded by depth edges, so no refinement moves a goal onto another
   object (a target on a pole in front of a box stays on the pole).
   ``d' = min(depth(p'), D_max)``.
2. **Bearing-aware range gating.** ``theta = atan((p'_x - c_x) / f_x)``, ``theta_max`` is half
   the horizontal FOV, ``d_f = d' exp(-0.5 (theta / (sigma_theta theta_max))^2)``,
   ``X_cam = d_f K^-1 [p'_x, p'_y, 1]^T`` and ``X_world = T_world_cam X_cam``.

Clearance, exactly
------------------
The obstacle rule and its defaults are documented in :mod:`planning.verifier_config`. A pixel is
*feasible* when its viewing ray passes at least ``r`` from every obstacle point ``Y_j`` (the
back-projection of obstacle pixel ``j``, through the pixel centre). That holds iff the angle
between the rays exceeds ``beta_j = asin(r / |Y_j|)``; every ray within ``beta_j`` of obstacle
``j`` meets the normalized image plane inside the disc of radius ``tan(psi_j + beta_j) -
tan(psi_j)`` around ``j``'s image (``psi_j`` its off-axis angle; :func:`cone_radius_px`, about
``fx * r / z_j`` pixels, larger off-axis), so "outside every obstacle's disc" is a sufficient
pixel test. Distances on the normalized plane make the test exact for non-square pixels too.
The target pixel is checked exactly against every obstacle disc; when it fails, a conservative
feasibility map of the ROI is built (one distance transform per class of obstacles of similar
radius, each dilated by its class's largest radius, coarser grids for large radii with their
worst-case rounding subtracted), its nearest feasible pixel of the component is re-checked
exactly and then pulled back toward the target along the line joining them, by bisection with
the exact test (the map is a few pixels conservative; this recovers most of it). Because the
whole ray clears every obstacle, the returned goal -- wherever the gating puts it on the ray --
and the straight path to it from the camera are at least ``r`` from every obstacle surface
point visible in the depth image. A refined pixel must also have a depth reading and must not
be an obstacle itself.
Skipped refinement keeps ``p`` and shortens the range to the part of its ray that clears every
reading by ``r`` (exact, against the back-projected readings); a clear part shorter than
``min_range_m`` is rejected.

Conventions: pixels ``(u, v)`` with integer values at pixel centres (see
:mod:`planning.camera`); the depth and patch value at a continuous pixel are those of the pixel
that contains it (``round half up``). Patch ``(i, j)`` covers rows ``[i * patch_px, (i + 1) *
patch_px)`` and the same columns, in pixels of the depth image.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from planning.camera import CameraError, PinholeCamera
from planning.frames import FrameError, check_transform, transform_points
from planning.verifier_config import VerifierConfig, VerifierConfigError

__all__ = [
    "CandidateGoal",
    "RefinementNote",
    "RejectionReason",
    "VerificationRecord",
    "VerifiedGoal",
    "Verifier",
    "VerifierConfig",
    "VerifierConfigError",
    "VerifierInputError",
    "bearing_gate",
    "cone_radius_px",
    "surface_region",
]

logger = logging.getLogger(__name__)

_TINY_DEPTH = float(np.finfo(np.float32).tiny)
_MAX_DEPTH = float(np.finfo(np.float32).max)
#: A map pixel is feasible when its clearance slack exceeds this, pixels (float32 rounding).
_SLACK_EPS_PX = 1e-3
#: A ray is clear when it passes farther than r + this from every obstacle point, metres.
_CLEARANCE_EPS_M = 1e-9
#: The clear part of a ray stops this far before it enters a point's r-ball, metres (rounding).
_CLEAR_RANGE_MARGIN_M = 1e-6
#: Exact re-checks of refined candidates before giving up (a failure would be a bug; logged).
_MAX_EXACT_RECHECKS = 8
#: Searches per candidate: the target's rule, then once more with a refined pixel's stricter one.
_SEARCH_ROUNDS = 2
#: Ratio between the depth edges of the bands in which exact obstacles are collected.
_BAND_RATIO = 1.5


class VerifierInputError(ValueError):
    """A :class:`CandidateGoal` whose arrays do not fit together (message names the field)."""


class RefinementNote(str, enum.Enum):
    """Whether step 1 ran, in which mode, and why not."""

    SEMANTIC = "semantic"  #: ran with the similarity mask
    NO_FEATURES = "no_features"  #: ran geometric-only: the candidate carries no features
    DEGENERATE_FEATURE = "degenerate_feature"  #: ran geometric-only: feature at p zero or non-finite
    BEYOND_D_MAX = "beyond_d_max"  #: skipped: depth(p) > D_max
    NO_DEPTH_READING = "no_depth_reading"  #: skipped: p has no reading (0, NaN, inf)
    NOT_ATTEMPTED = "not_attempted"  #: the candidate was rejected before step 1


class RejectionReason(str, enum.Enum):
    """Why no goal was returned."""

    PIXEL_OUTSIDE_IMAGE = "pixel_outside_image"  #: p non-finite or outside the image
    INVALID_DEPTH_EVERYWHERE = "invalid_depth_everywhere"  #: no valid reading in the whole image
    NO_DEPTH_AT_TARGET = "no_depth_at_target"  #: p has no reading and reject_no_reading is set
    NO_FEASIBLE_PIXEL = "no_feasible_pixel"  #: refinement found no feasible pixel in the component
    UNREFINED_TARGET_UNSAFE = "unrefined_target_unsafe"  #: refinement skipped and p's ray is not clear


_NAN = float("nan")


@dataclass(frozen=True)
class CandidateGoal:
    """``G_c = [p_x, p_y, depth_t, f_t, pose_t]``: one VLM target with the frame it points into.

    Attributes
    ----------
    pixel_uv : (float, float)
        Target pixel ``(u, v)`` in the depth image, pixels (may be anywhere; outside the image
        gives a rejection, not an error).
    depth_m : array, shape (H, W), float32
        Z-depth in metres, camera optical frame; 0, NaN, inf mean no reading. A float dtype
        (:meth:`PinholeCamera.check_depth`: integer counts and millimetre frames are refused).
        Coerced to a C-contiguous float32 array on construction.
    features : array, shape (Hp, Wp, C), or None
        Per-patch vision features (any real dtype); None selects the geometric-only mode.
    patch_px : float
        Patch side in pixels of the depth image; the grid must cover the image:
        ``Hp == ceil(H / patch_px)`` and ``Wp == ceil(W / patch_px)``.
    T_world_cam : array, shape (4, 4)
        Camera optical frame to world (ENU) at the frame's time.
    camera : PinholeCamera
        Intrinsics of the depth image.

    Raises
    ------
    VerifierInputError
        On any shape, type or value mismatch (the message names the field).
    """

    pixel_uv: tuple[float, float]
    depth_m: np.ndarray
    features: np.ndarray | None
    patch_px: float
    T_world_cam: np.ndarray
    camera: PinholeCamera

    def __post_init__(self) -> None:
        if not isinstance(self.camera, PinholeCamera):
            raise VerifierInputError(f"camera must be a PinholeCamera, got {type(self.camera).__name__}")
        try:
            uv = tuple(float(x) for x in self.pixel_uv)
        except (TypeError, ValueError):
            raise VerifierInputError(f"pixel_uv must be two numbers (u, v), got {self.pixel_uv!r}") from None
        if len(uv) != 2:
            raise VerifierInputError(f"pixel_uv must be two numbers (u, v), got {len(uv)} values")
        object.__setattr__(self, "pixel_uv", uv)

        depth = np.asarray(self.depth_m)
        if depth.ndim != 2 or depth.shape != self.camera.shape:
            raise VerifierInputError(f"depth_m must have shape {self.camera.shape} (camera.shape), got {depth.shape}")
        try:  # float metres: an integer frame (counts) or a millimetre frame would put goals through walls
            depth = self.camera.check_depth(depth, "depth_m")
        except CameraError as exc:
            raise VerifierInputError(str(exc)) from None
        object.__setattr__(self, "depth_m", np.ascontiguousarray(depth, dtype=np.float32))

        try:
            patch_px = float(self.patch_px)
        except (TypeError, ValueError):
            raise VerifierInputError(f"patch_px must be a number, got {self.patch_px!r}") from None
        if not (math.isfinite(patch_px) and patch_px > 0.0):
            raise VerifierInputError(f"patch_px must be finite and > 0, got {self.patch_px}")
        object.__setattr__(self, "patch_px", patch_px)

        if self.features is not None:
            feats = np.asarray(self.features)
            if feats.ndim != 3 or feats.shape[2] < 1:
                raise VerifierInputError(f"features must have shape (Hp, Wp, C) with C >= 1, got {feats.shape}")
            if not (np.issubdtype(feats.dtype, np.floating) or np.issubdtype(feats.dtype, np.integer)):
                raise VerifierInputError(f"features must be a real array, got dtype {feats.dtype}")
            h, w = self.camera.shape
            expected = (math.ceil(h / patch_px - 1e-9), math.ceil(w / patch_px - 1e-9))
            if feats.shape[:2] != expected:
                raise VerifierInputError(
                    f"features grid must be {expected} patches for a {h} x {w} image with patch_px={patch_px:g}, "
                    f"got {feats.shape[:2]}"
                )
            object.__setattr__(self, "features", feats)

        try:
            T = check_transform(self.T_world_cam, "T_world_cam")
        except FrameError as exc:
            raise VerifierInputError(str(exc)) from None
        object.__setattr__(self, "T_world_cam", T)


@dataclass(frozen=True)
class VerificationRecord:
    """What the verifier did with one candidate (all pixels ``(u, v)``, depths z in metres).

    Attributes
    ----------
    pixel_uv : (float, float)
        Original target pixel p.
    refined_uv : (float, float) or None
        Refined pixel p' (equal to p when it stayed put or refinement was skipped); None when
        no pixel was selected.
    pixel_shift_px : float
        ``|p' - p|`` in pixels; NaN when no pixel was selected.
    refinement_ran : bool
        Whether step 1 (the search for p') ran.
    refinement_note : RefinementNote
        Mode it ran in, or why it did not run.
    geometric_only : bool
        True when the search ignored semantics (no features, or a degenerate feature at p).
    component_size_px : int
        Pixels in the semantic component of p inside the ROI (the whole ROI when geometric-only);
        0 when refinement did not run.
    target_depth_m : float
        ``d = depth(p)``; NaN when p has no reading or lies outside the image.
    obstacle_threshold_m : float
        Depth below which valid readings counted as obstacles (see
        :meth:`VerifierConfig.obstacle_threshold_m`); NaN when not reached.
    ray_clearance_m : float
        Distance from the nearest obstacle point to the viewing ray of p' (of p for a rejection
        after its check), metres: > r when accepted, inf when no obstacle comes near; NaN when
        not computed.
    refined_depth_m : float
        ``d' = min(depth(p'), D_max)`` (D_max when refinement was skipped); NaN when rejected.
    bearing_rad : float
        ``theta = atan((p'_x - c_x) / f_x)``; NaN when rejected.
    gating_factor : float
        ``exp(-0.5 (theta / (sigma_theta theta_max))^2)``; NaN when rejected.
    range_m : float
        ``d_f = d' * gating_factor``, z-depth of the goal in the camera frame; NaN when rejected.
    rejection : RejectionReason or None
        Why the candidate was rejected; None when accepted.
    clear_range_m : float
        Skipped refinement only: z-depth at which ``p``'s ray first comes within r of a reading
        (or of the surface bounding an unread pixel), metres; inf when nothing limits it; NaN
        when refinement ran or the candidate was rejected before.
    bound_depth_m : float
        Unread target only: the depth of the surface around the hole (smallest reading on the
        border of the no-reading region in the ROI), metres; NaN otherwise.
    """

    pixel_uv: tuple[float, float]
    refined_uv: tuple[float, float] | None
    pixel_shift_px: float
    refinement_ran: bool
    refinement_note: RefinementNote
    geometric_only: bool
    component_size_px: int
    target_depth_m: float
    obstacle_threshold_m: float
    ray_clearance_m: float
    refined_depth_m: float
    bearing_rad: float
    gating_factor: float
    range_m: float
    rejection: RejectionReason | None
    clear_range_m: float = float("nan")
    bound_depth_m: float = float("nan")


@dataclass(frozen=True)
class VerifiedGoal:
    """The verifier's answer.

    Attributes
    ----------
    goal_world : array, shape (3,), metres, world frame (ENU); None when rejected
    accepted : bool
    record : VerificationRecord
    """

    goal_world: np.ndarray | None
    accepted: bool
    record: VerificationRecord


# -- pure geometry -------------------------------------------------------------------------------


def bearing_gate(theta_rad, theta_max_rad: float, sigma_theta: float):
    """Range gating factor ``exp(-0.5 * (theta / (sigma_theta * theta_max))^2)``.

    Parameters
    ----------
    theta_rad : float or array, bearing of the target in radians (any value, beyond the FOV too)
    theta_max_rad : float, half the horizontal FOV, radians, > 0
    sigma_theta : float, relative width, > 0

    Returns
    -------
    float or array in (0, 1], same shape as ``theta_rad``.
    """
    x = np.asarray(theta_rad, dtype=float) / (sigma_theta * theta_max_rad)
    g = np.exp(-0.5 * x * x)
    return float(g) if np.ndim(g) == 0 else g


def cone_radius_px(tan_psi, range_m, clearance_m: float, focal_px: float):
    """Pixel radius around an obstacle pixel containing every ray that passes within
    ``clearance_m`` of its 3D point.

    An obstacle point at range ``rho`` (distance from the camera centre) seen at off-axis angle
    ``psi`` is within ``r`` of a ray iff the ray is within ``beta = asin(r / rho)`` of the
    point's own ray. Those rays meet the normalized image plane inside an ellipse whose farthest
    point from the obstacle's image lies on the outward radial line at distance
    ``tan(psi + beta) - tan(psi) = tan(beta) (1 + tan^2 psi) / (1 - tan(psi) tan(beta))``, and a
    normalized distance spans at most ``max(fx, fy)`` pixels per unit. On the optical axis this
    is ``f r / sqrt(rho^2 - r^2)``, i.e. ``fx * r / depth`` to first order.

    Parameters
    ----------
    tan_psi : float or array, tangent of the obstacle's off-axis angle, >= 0
    range_m : float or array, distance of the obstacle point from the camera centre, metres
    clearance_m : float, r, metres
    focal_px : float, ``max(fx, fy)``, pixels

    Returns
    -------
    float or array of radii in pixels; ``inf`` when the cone reaches 90 deg off-axis or the
    camera itself is within ``r`` of the point.
    """
    t = np.asarray(tan_psi, dtype=float)
    rng = np.asarray(range_m, dtype=float)
    rad = focal_px * _rho_from_squares(t * t, rng * rng, clearance_m)
    return float(rad) if np.ndim(rad) == 0 else rad


def _rho_from_squares(tan2, range2, clearance_m: float):
    """Normalized cone radius ``tan(psi + beta) - tan(psi)`` from ``tan(psi)^2`` and range^2."""
    tan2 = np.asarray(tan2, dtype=float)
    range2 = np.asarray(range2, dtype=float)
    r = clearance_m
    den = np.sqrt(np.maximum(range2 - r * r, 0.0)) - np.sqrt(tan2) * r
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0.0, r * (1.0 + tan2) / np.where(den > 0.0, den, 1.0), np.inf)


@dataclass(frozen=True)
class _Obstacles:
    """Obstacle pixels whose clearance disc can reach a pixel box, with their 3D points.

    A ray through pixel ``q`` clears obstacle ``j`` by r when the angle between the rays exceeds
    ``beta_j``; the disc of normalized radius ``rho_j`` (``fx * rho_j`` column pixels,
    ``fy * rho_j`` rows) around ``j`` holds every ray that does not.
    """

    rows: np.ndarray  # (n,) int, image rows
    cols: np.ndarray  # (n,) int, image columns
    rho: np.ndarray  # (n,) float, normalized cone radius, may hold inf
    points: np.ndarray  # (n, 3) float, metres, camera optical frame

    @property
    def empty(self) -> bool:
        return self.rows.size == 0

    def ray_clearance_m(self, camera: PinholeCamera, u: float, v: float) -> float:
        """Smallest distance from these points to the half-line from the camera centre through
        pixel (u, v), metres; inf without points. Exact (no pixel-space approximation)."""
        if self.empty:
            return math.inf
        d = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
        d /= math.sqrt(float(d @ d))
        P = self.points
        along = np.maximum(P @ d, 0.0)
        dist2 = np.einsum("ij,ij->i", P, P) - along * along
        return math.sqrt(max(float(dist2.min()), 0.0))


def _tan2_max(camera: PinholeCamera, r0: int, r1: int, c0: int, c1: int) -> float:
    """Largest ``tan(psi)^2`` over the pixel centres of rows [r0, r1) and columns [c0, c1)."""
    x = max(abs(c0 - camera.cx), abs(c1 - 1 - camera.cx)) / camera.fx
    y = max(abs(r0 - camera.cy), abs(r1 - 1 - camera.cy)) / camera.fy
    return x * x + y * y


def _rho_scalar(tan2: float, range2: float, clearance_m: float) -> float:
    """Scalar :func:`_rho_from_squares` (no numpy overhead in the window loop)."""
    r = clearance_m
    den = math.sqrt(max(range2 - r * r, 0.0)) - math.sqrt(tan2) * r
    return r * (1.0 + tan2) / den if den > 0.0 else math.inf


def _nearest_obstacle_depth(depth: np.ndarray, threshold_m: float) -> float | None:
    """Smallest valid depth below ``threshold_m`` in the whole image, or None without obstacles."""
    # Largest float32 strictly below the threshold: inRange is inclusive, the rule is "< T".
    upper = float(np.nextafter(np.float32(threshold_m), np.float32(0.0)))
    if upper < _TINY_DEPTH:
        return None
    obstacle_mask = cv2.inRange(depth, _TINY_DEPTH, upper)  # 0 / 255; NaN and inf are outside
    if cv2.countNonZero(obstacle_mask) == 0:
        return None
    return float(cv2.minMaxLoc(depth, obstacle_mask)[0])


def _depth_bands(
    depth: np.ndarray,
    camera: PinholeCamera,
    box: tuple[int, int, int, int],
    threshold_m: float,
    z_min: float | None,
    clearance_m: float,
    band_ratio: float,
):
    """Depth bands of the obstacles that can reach ``box``, nearest last.

    Yields ``(lo, hi, window, rho_max)``: the band holds valid depths in ``[lo, hi]`` (float32
    edges, together exactly the obstacle rule ``0 < z < threshold_m``), ``window = (r0, r1, c0,
    c1)`` is the only part of the image where its obstacles can reach ``box``, and ``rho_max``
    bounds the normalized cone radius of every obstacle of the band inside the window (inf when
    unbounded). The window is the box grown by ``fy * rho_max`` rows and ``fx * rho_max``
    columns, shrunk to a fixed point from the whole image: the radius grows with the off-axis
    angle and shrinks with range, and obstacles outside a window were already out of reach.
    ``z_min`` is :func:`_nearest_obstacle_depth` (None: no obstacle, nothing is yielded).
    """
    if z_min is None:
        return
    upper = float(np.nextafter(np.float32(threshold_m), np.float32(0.0)))
    h, w = depth.shape
    fx, fy = camera.fx, camera.fy
    r0, r1, c0, c1 = box
    hi = upper
    while True:
        lo_edge = hi / band_ratio
        last = lo_edge <= z_min
        lo = _TINY_DEPTH if last else float(np.nextafter(np.float32(lo_edge), np.float32(np.inf)))
        z_lo2 = max(lo, z_min) ** 2  # range >= z-depth >= this band's nearest depth
        window, rho_max = (0, h, 0, w), math.inf
        for _ in range(4):
            rho_max = _rho_scalar(_tan2_max(camera, *window), z_lo2, clearance_m)
            if not math.isfinite(rho_max):
                break
            pr, pc = int(math.ceil(fy * rho_max)), int(math.ceil(fx * rho_max))
            shrunk = (max(0, r0 - pr), min(h, r1 + pr), max(0, c0 - pc), min(w, c1 + pc))
            if shrunk == window:
                break
            window = shrunk
            rho_max = _rho_scalar(_tan2_max(camera, *window), z_lo2, clearance_m)
        yield lo, hi, window, rho_max
        if last:
            return
        hi = float(np.nextafter(np.float32(lo), np.float32(0.0)))


def _gather_obstacles(
    depth: np.ndarray,
    camera: PinholeCamera,
    box: tuple[int, int, int, int],
    threshold_m: float,
    z_min: float | None,
    clearance_m: float,
) -> _Obstacles:
    """Every obstacle pixel (valid depth < ``threshold_m``) whose clearance region reaches
    ``box``, with its exact cone radius (see :func:`_depth_bands` for the search windows)."""
    fx, fy = camera.fx, camera.fy
    rows_all, cols_all, rho_all, pts_all = [], [], [], []
    r0, r1, c0, c1 = box
    for lo, hi, (wr0, wr1, wc0, wc1), _ in _depth_bands(depth, camera, box, threshold_m, z_min, clearance_m, _BAND_RATIO):
        idx = np.flatnonzero(cv2.inRange(depth[wr0:wr1, wc0:wc1], lo, hi) != 0)
        if idx.size == 0:
            continue
        rr, cc = np.divmod(idx, wc1 - wc0)
        rows = rr + wr0
        cols = cc + wc0
        z = depth[rows, cols].astype(np.float64)
        xn = (cols - camera.cx) / fx
        yn = (rows - camera.cy) / fy
        tan2 = xn * xn + yn * yn
        rho = _rho_from_squares(tan2, z * z * (1.0 + tan2), clearance_m)
        # The cone image lies within fx * rho columns and fy * rho rows of the obstacle.
        d_row = np.maximum(np.maximum(r0 - rows, rows - (r1 - 1)), 0)
        d_col = np.maximum(np.maximum(c0 - cols, cols - (c1 - 1)), 0)
        keep = (d_row <= fy * rho) & (d_col <= fx * rho)
        rows_all.append(rows[keep])
        cols_all.append(cols[keep])
        rho_all.append(rho[keep])
        zk = z[keep]
        pts_all.append(np.stack([xn[keep] * zk, yn[keep] * zk, zk], axis=1))
    if not rows_all:
        return _Obstacles(np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0), np.zeros((0, 3)))
    return _Obstacles(
        np.concatenate(rows_all), np.concatenate(cols_all), np.concatenate(rho_all), np.concatenate(pts_all)
    )


_CROSS_3 = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


def _slack_map(
    depth: np.ndarray,
    camera: PinholeCamera,
    box: tuple[int, int, int, int],
    threshold_m: float,
    z_min: float | None,
    clearance_m: float,
    radius_ratio: float,
) -> np.ndarray:
    """Lower bound of the clearance slack ``min_j (dist(q, j) - fx rho_j)`` for every pixel
    ``q`` of ``box`` that is not itself an obstacle, in column pixels (see :class:`_Obstacles`).

    The exact cone radius ``rho`` of every obstacle pixel of the search window (the box grown
    by the largest radius any obstacle can have, as in :func:`_depth_bands`) is split into
    classes ``[rho_0 g^k, rho_0 g^(k+1))`` with ``g = radius_ratio``; each class is dilated by
    its upper edge through one exact Euclidean distance transform of the class's boundary pixels
    (those with a 4-neighbour outside the class: the class pixel nearest to any pixel outside
    the class is always one of them). The transform runs on a grid whose rows are scaled by
    ``fx / fy`` (isotropic on the normalized image plane) with cells of ``s`` column pixels (1
    below 24 px of radius, 2 below 96 px, else 4); the worst-case offset of two points within
    their cells is subtracted. Values at obstacle pixels of the box are meaningless: callers
    exclude them.
    """
    r0, r1, c0, c1 = box
    slack = np.full((r1 - r0, c1 - c0), np.inf, dtype=np.float32)
    if z_min is None:
        return slack
    h, w = depth.shape
    fx, fy = camera.fx, camera.fy
    # One window for every obstacle: the nearest depth's band window contains all the others.
    # Shrink it while the nearest obstacle inside it is farther than the one it was sized for:
    # obstacles left outside are then out of reach (their depth is at least that nearest one).
    upper = float(np.nextafter(np.float32(threshold_m), np.float32(0.0)))
    while True:
        *_, (_, _, (wr0, wr1, wc0, wc1), _) = _depth_bands(depth, camera, box, threshold_m, z_min, clearance_m, math.inf)
        zw = depth[wr0:wr1, wc0:wc1]
        obst = cv2.inRange(zw, _TINY_DEPTH, upper)
        if cv2.countNonZero(obst) == 0:
            return slack
        z_in = float(cv2.minMaxLoc(zw, obst)[0])
        if z_in <= z_min:
            break
        z_min = z_in
    xn2 = (((np.arange(wc0, wc1) - camera.cx) / fx) ** 2).astype(np.float32)
    yn2 = (((np.arange(wr0, wr1) - camera.cy) / fy) ** 2).astype(np.float32)
    tan2 = yn2[:, None] + xn2[None, :]
    r = np.float32(clearance_m)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        zz = np.where(obst != 0, zw, np.float32(np.inf))  # non-obstacles: infinite range, rho 0
        den = np.sqrt(np.maximum(zz * zz * (1.0 + tan2) - r * r, 0.0)) - np.sqrt(tan2) * r
        rho = np.where(den > 0.0, r * (1.0 + tan2) / den, np.float32(np.inf)).astype(np.float32)
    rho_hi = float(rho.max())
    if not math.isfinite(rho_hi):
        slack[:] = -np.inf
        return slack
    # float32 rounding of rho: every radius is widened by a relative 1e-5 (0 stays 0).
    rho *= np.float32(1.0 + 1e-5)
    rho_lo = float(cv2.minMaxLoc(rho, obst)[0])
    aspect = fx / fy
    edge_lo = rho_lo
    while edge_lo <= rho_hi * (1.0 + 2e-5):
        edge_hi = edge_lo * radius_ratio
        radius = fx * edge_hi
        pr, pc = int(math.ceil(fy * edge_hi)), int(math.ceil(fx * edge_hi))
        sr0, sr1 = max(wr0, r0 - pr), min(wr1, r1 + pr)
        sc0, sc1 = max(wc0, c0 - pc), min(wc1, c1 + pc)
        cls = cv2.inRange(rho[sr0 - wr0 : sr1 - wr0, sc0 - wc0 : sc1 - wc0], edge_lo, edge_hi)
        edge_lo = float(np.nextafter(np.float32(edge_hi), np.float32(np.inf)))
        if cv2.countNonZero(cls) == 0:
            continue
        edge = cv2.subtract(cls, cv2.erode(cls, _CROSS_3))
        rr, cc = np.divmod(np.flatnonzero(edge != 0), sc1 - sc0)
        s = 1 if radius < 24.0 else (2 if radius < 96.0 else 4)
        # Cell offsets differ by at most s - 1 along columns (integer) and, with scaled rows,
        # by less than s along rows (s - 1 when the scale is exactly 1).
        row_off = s - 1.0 if aspect == 1.0 else float(s)
        loss = math.hypot(s - 1.0, row_off)
        n_rows = int(math.floor((sr1 - 1 - sr0) * aspect / s)) + 1
        n_cols = (sc1 - 1 - sc0) // s + 1
        grid = np.ones((n_rows, n_cols), dtype=np.uint8)
        grid[np.floor(rr * aspect / s).astype(np.intp), cc // s] = 0
        dt = cv2.distanceTransform(grid, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        iy = np.floor((np.arange(r0, r1) - sr0) * aspect / s).astype(np.intp)
        ix = (np.arange(c0, c1) - sc0) // s
        np.minimum(slack, s * dt[np.ix_(iy, ix)] - (loss + radius), out=slack)
    return slack


def _pixel_box(u: float, v: float) -> tuple[int, int, int, int]:
    """Half-open box of the integer rows and columns within one pixel of (u, v)."""
    return (int(math.floor(v)), int(math.floor(v)) + 2, int(math.floor(u)), int(math.floor(u)) + 2)


def _segment_box(u: float, v: float, col: int, row: int) -> tuple[int, int, int, int]:
    """Half-open box containing the pixels of the segment (u, v) -> (col, row), one pixel wider."""
    return (
        int(math.floor(min(v, row))) - 1,
        int(math.ceil(max(v, row))) + 2,
        int(math.floor(min(u, col))) - 1,
        int(math.ceil(max(u, col))) + 2,
    )


def _pull_toward_target(
    obstacles: _Obstacles,
    camera: PinholeCamera,
    clearance_m: float,
    allowed: np.ndarray,
    box: tuple[int, int, int, int],
    uv: tuple[float, float],
    found: tuple[int, int],
    found_clearance_m: float,
) -> tuple[int, int, float]:
    """Move a feasible pixel back toward the target along the line joining them.

    The feasibility map is conservative (discs around the cone images, radius classes, coarse
    cells), so the nearest pixel it accepts can lie a few pixels beyond the exact clearance
    boundary. The pixels of the line from the target ``uv`` to ``found`` that are ``allowed``
    (in the component, with a reading, not an obstacle) are bisected with the exact ray
    clearance; only a pixel whose ray clears every obstacle by ``clearance_m`` is returned.

    Returns ``(row, col, clearance_m)`` of the chosen pixel (``found`` when nothing closer passes).
    """
    r0, _, c0, _ = box
    fr, fc = found
    n = int(math.ceil(math.hypot(fc - uv[0], fr - uv[1])))
    if n < 2:
        return fr, fc, found_clearance_m
    t = np.linspace(0.0, 1.0, n + 1)
    rows = np.floor(uv[1] + t * (fr - uv[1]) + 0.5).astype(np.intp)
    cols = np.floor(uv[0] + t * (fc - uv[0]) + 0.5).astype(np.intp)
    line = np.unique(np.stack([rows, cols], axis=1), axis=0)
    order = np.argsort(np.hypot(line[:, 1] - uv[0], line[:, 0] - uv[1]), kind="stable")
    line = line[order]
    line = line[allowed[line[:, 0] - r0, line[:, 1] - c0]]
    # line[-1] is `found` (feasible); look for the first feasible pixel assuming one crossing.
    lo, hi, best = -1, len(line) - 1, (fr, fc, found_clearance_m)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        clearance = obstacles.ray_clearance_m(camera, float(line[mid, 1]), float(line[mid, 0]))
        if clearance > clearance_m + _CLEARANCE_EPS_M:
            hi, best = mid, (int(line[mid, 0]), int(line[mid, 1]), clearance)
        else:
            lo = mid
    return best


# -- the verifier --------------------------------------------------------------------------------


class Verifier:
    """Semantic-guided refinement plus bearing-aware gating (pure: no state across calls).

    Parameters
    ----------
    config : VerifierConfig
    """

    def __init__(self, config: VerifierConfig | None = None) -> None:
        if config is None:
            config = VerifierConfig()
        if not isinstance(config, VerifierConfig):
            raise VerifierConfigError(f"config must be a VerifierConfig, got {type(config).__name__}")
        self.config = config

    def verify(self, candidate: CandidateGoal) -> VerifiedGoal:
        """Refine, gate and lift one candidate goal; see the module docs for the algorithm.

        Returns
        -------
        VerifiedGoal
            ``goal_world`` (3,) in metres in the world frame when accepted, else None with
            ``record.rejection`` set. Never raises for a well-formed :class:`CandidateGoal`.
        """
        if not isinstance(candidate, CandidateGoal):
            raise VerifierInputError(f"candidate must be a CandidateGoal, got {type(candidate).__name__}")
        cfg = self.config
        cam = candidate.camera
        depth = candidate.depth_m
        u, v = candidate.pixel_uv
        h, w = depth.shape
        if not bool(cam.in_image((u, v))):
            return self._reject(candidate, RejectionReason.PIXEL_OUTSIDE_IMAGE)
        col, row = int(math.floor(u + 0.5)), int(math.floor(v + 0.5))
        half = cfg.roi_px // 2
        roi = (max(0, row - half), min(h, row - half + cfg.roi_px), max(0, col - half), min(w, col - half + cfg.roi_px))

        d = float(depth[row, col])
        has_reading = math.isfinite(d) and d > 0.0
        if not has_reading:
            r0, r1, c0, c1 = roi
            roi_depth = depth[r0:r1, c0:c1]
            if not _any_valid(roi_depth) and not _any_valid(depth):
                return self._reject(candidate, RejectionReason.INVALID_DEPTH_EVERYWHERE)
            if cfg.reject_no_reading:
                return self._reject(candidate, RejectionReason.NO_DEPTH_AT_TARGET)
            bound = _hole_bound_depth(depth, roi, row, col)
            if bound is None:  # nothing known about this ray: never open space
                return self._reject(
                    candidate, RejectionReason.NO_DEPTH_AT_TARGET, note=RefinementNote.NO_DEPTH_READING
                )
            return self._skip(candidate, RefinementNote.NO_DEPTH_READING, _NAN, bound)
        if d > cfg.d_max_m:
            return self._skip(candidate, RefinementNote.BEYOND_D_MAX, d, _NAN)

        # -- step 1: semantic-guided refinement ------------------------------------------------
        r_m = cfg.clearance_radius_m
        surface = _SurfaceRegion.grow(depth, row, col, cfg.surface_jump_ratio, cfg.foreground_margin_m, roi, cfg.roi_px)
        comp, note = self._component(candidate, roi, row, col, surface)
        component_size = int(np.count_nonzero(comp))
        geometric_only = note is not RefinementNote.SEMANTIC
        view = _ObstacleView.at(depth, surface, d, cfg)
        clearance_p = view.gather(cam, _pixel_box(u, v), r_m).ray_clearance_m(cam, u, v)
        clear_p = self._near_target_range(candidate, view, u, v, d)
        if clearance_p > r_m + _CLEARANCE_EPS_M and not clear_p < cfg.min_range_m:  # already feasible: stays put
            return self._accept(
                candidate, (u, v), min(d, cfg.d_max_m), note, geometric_only, component_size, d, view.threshold_m,
                clearance_p, clear_range_m=clear_p,
            )

        r0, r1, c0, c1 = roi
        roi_depth = depth[r0:r1, c0:c1]
        search = view
        for _round in range(_SEARCH_ROUNDS):
            found, stricter = self._search(candidate, roi, comp, roi_depth, surface, search)
            if found is not None:
                (qr, qc), own, clearance_q, clear_q = found
                return self._accept(
                    candidate, (float(qc), float(qr)), min(float(depth[qr, qc]), cfg.d_max_m), note, geometric_only,
                    component_size, d, own.threshold_m, clearance_q, clear_range_m=clear_q,
                )
            if stricter is None or stricter.threshold_m <= search.threshold_m:
                break
            # A pixel passed the target's rule but not its own (a farther surface, a higher
            # threshold): search again with the stricter rule.
            search = stricter
        return self._reject(
            candidate,
            RejectionReason.NO_FEASIBLE_PIXEL,
            note=note,
            ran=True,
            geometric_only=geometric_only,
            component_size=component_size,
            target_depth_m=d,
            threshold_m=view.threshold_m,
            clearance_m=clearance_p,
        )

    # -- helpers ---------------------------------------------------------------------------------
    def _search(self, candidate, roi, comp, roi_depth, surface, view):
        """Nearest pixel of ``comp`` whose ray clears the obstacles of ``view`` *and* of the rule
        evaluated at its own depth. Returns ``(((row, col), own_view, clearance) or None,
        stricter_view or None)``; the second is the rule of a pixel that failed only its own."""
        cfg = self.config
        cam = candidate.camera
        depth = candidate.depth_m
        u, v = candidate.pixel_uv
        r_m = cfg.clearance_radius_m
        r0, r1, c0, c1 = roi
        slack_map = _slack_map(view.depth_m, cam, roi, view.threshold_m, view.z_min, r_m, cfg.radius_class_ratio)
        with np.errstate(invalid="ignore"):
            # Candidates need a reading and must not be obstacles themselves.
            allowed = comp & (roi_depth > 0) & np.isfinite(roi_depth) & ~(view.depth_m[r0:r1, c0:c1] < view.threshold_m)
        rr, cc = np.nonzero(allowed & (slack_map > _SLACK_EPS_PX))
        stricter = None
        if not rr.size:
            return None, None
        dist2 = (cc + c0 - u) ** 2 + (rr + r0 - v) ** 2
        for k in np.argsort(dist2, kind="stable")[:_MAX_EXACT_RECHECKS]:
            qr, qc = int(rr[k] + r0), int(cc[k] + c0)
            near_line = view.gather(cam, _segment_box(u, v, qc, qr), r_m)
            clearance_q = near_line.ray_clearance_m(cam, float(qc), float(qr))
            if not clearance_q > r_m + _CLEARANCE_EPS_M:
                logger.error("verifier: slack map accepted pixel (%d, %d) that fails the exact check", qc, qr)
                continue
            pulled = _pull_toward_target(near_line, cam, r_m, allowed, roi, (u, v), (qr, qc), clearance_q)
            for pr_, pc_, c_ in (pulled, (qr, qc, clearance_q)):
                # The obstacle rule evaluated at the refined pixel itself.
                own = _ObstacleView.at(depth, surface, float(depth[pr_, pc_]), cfg)
                own_clear = own.gather(cam, _pixel_box(pc_, pr_), r_m).ray_clearance_m(cam, float(pc_), float(pr_))
                if own_clear > r_m + _CLEARANCE_EPS_M and not bool(own.depth_m[pr_, pc_] < own.threshold_m):
                    clear = self._near_target_range(candidate, own, float(pc_), float(pr_), float(depth[pr_, pc_]))
                    if not clear < cfg.min_range_m:
                        return ((pr_, pc_), own, min(own_clear, c_), clear), None
                    continue
                if stricter is None or own.threshold_m > stricter.threshold_m:
                    stricter = own
            logger.debug("verifier: pixel (%d, %d) fails the obstacle rule at its own depth", qc, qr)
        return None, stricter

    def _near_target_range(self, candidate: CandidateGoal, view: "_ObstacleView", u: float, v: float, d: float) -> float:
        """Clear part of the ray for a goal on a target whose surface was exempted from the
        near field (``view.exempted``): the goal stands in front of it, r clear of every reading,
        instead of on it. NaN when nothing was exempted (the goal stays at ``d'``, paper)."""
        if not view.exempted:
            return _NAN
        cfg = self.config
        return _clear_range_z(candidate.depth_m, candidate.camera, u, v, min(d, cfg.d_max_m), cfg.clearance_radius_m, _NAN)

    def _skip(self, candidate: CandidateGoal, note: RefinementNote, d: float, bound_m: float) -> VerifiedGoal:
        """Refinement skipped (far or unread target): ``p' = p``, range gated to the clear ray."""
        cfg = self.config
        cam = candidate.camera
        u, v = candidate.pixel_uv
        d_prime = min(d if math.isfinite(d) else bound_m, cfg.d_max_m)
        clear = _clear_range_z(candidate.depth_m, cam, u, v, d_prime, cfg.clearance_radius_m, bound_m)
        if not clear >= cfg.min_range_m:
            return self._reject(
                candidate,
                RejectionReason.UNREFINED_TARGET_UNSAFE,
                note=note,
                target_depth_m=d,
                threshold_m=_NAN,
                clearance_m=_NAN,
                clear_range_m=clear,
                bound_depth_m=bound_m,
            )
        return self._accept(
            candidate, (u, v), d_prime, note, False, 0, d, _NAN, _NAN, clear_range_m=clear, bound_depth_m=bound_m
        )

    def _component(
        self, candidate: CandidateGoal, roi, row: int, col: int, surface: "_SurfaceRegion"
    ) -> tuple[np.ndarray, RefinementNote]:
        """Boolean ROI mask of the component containing (row, col), and the mode.

        With features: the semantic component (cosine >= tau, connected). Without, or with a
        degenerate feature at p: the target's surface (depth-continuous with p) inside the ROI.
        """
        r0, r1, c0, c1 = roi
        feats = candidate.features
        if feats is None:
            return surface.crop(roi), RefinementNote.NO_FEATURES
        hp, wp = feats.shape[:2]
        patch = candidate.patch_px
        pi = np.minimum((np.arange(r0, r1) / patch).astype(np.intp), hp - 1)
        pj = np.minimum((np.arange(c0, c1) / patch).astype(np.intp), wp - 1)
        ip, jp = min(int(row / patch), hp - 1), min(int(col / patch), wp - 1)
        f_p = np.asarray(feats[ip, jp], dtype=np.float64)
        norm_p = float(np.linalg.norm(f_p))
        if not (math.isfinite(norm_p) and norm_p > 0.0):
            return surface.crop(roi), RefinementNote.DEGENERATE_FEATURE
        i0, i1, j0, j1 = int(pi[0]), int(pi[-1]) + 1, int(pj[0]), int(pj[-1]) + 1
        block = np.asarray(feats[i0:i1, j0:j1], dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            sim = (block @ f_p) / (np.linalg.norm(block, axis=-1) * norm_p)
            patch_mask = sim >= self.config.tau  # NaN (zero or non-finite features) -> False
        patch_mask[ip - i0, jp - j0] = True  # p is always similar to itself
        pix_mask = patch_mask[np.ix_(pi - i0, pj - j0)].astype(np.uint8)
        _, labels = cv2.connectedComponents(pix_mask, connectivity=self.config.connectivity)
        return labels == labels[row - r0, col - c0], RefinementNote.SEMANTIC

    def _accept(
        self,
        candidate: CandidateGoal,
        uv_refined: tuple[float, float],
        d_prime: float,
        note: RefinementNote,
        geometric_only: bool,
        component_size: int,
        target_depth_m: float,
        threshold_m: float,
        clearance_m: float,
        *,
        clear_range_m: float = _NAN,
        bound_depth_m: float = _NAN,
    ) -> VerifiedGoal:
        cfg = self.config
        cam = candidate.camera
        u2, v2 = uv_refined
        theta = math.atan((u2 - cam.cx) / cam.fx)
        gate = bearing_gate(theta, 0.5 * cam.hfov_rad, cfg.sigma_theta)
        d_f = d_prime * gate
        if math.isfinite(clear_range_m):
            d_f = min(d_f, clear_range_m)
        X_cam = cam.back_project(np.array([u2, v2]), d_f)
        X_world = transform_points(candidate.T_world_cam, X_cam)
        u, v = candidate.pixel_uv
        ran = note in (RefinementNote.SEMANTIC, RefinementNote.NO_FEATURES, RefinementNote.DEGENERATE_FEATURE)
        record = VerificationRecord(
            pixel_uv=(u, v),
            refined_uv=(u2, v2),
            pixel_shift_px=float(math.hypot(u2 - u, v2 - v)),
            refinement_ran=ran,
            refinement_note=note,
            geometric_only=geometric_only,
            component_size_px=component_size,
            target_depth_m=float(target_depth_m),
            obstacle_threshold_m=float(threshold_m),
            ray_clearance_m=float(clearance_m),
            refined_depth_m=float(d_prime),
            bearing_rad=float(theta),
            gating_factor=float(gate),
            range_m=float(d_f),
            rejection=None,
            clear_range_m=float(clear_range_m),
            bound_depth_m=float(bound_depth_m),
        )
        return VerifiedGoal(goal_world=X_world, accepted=True, record=record)

    def _reject(
        self,
        candidate: CandidateGoal,
        reason: RejectionReason,
        *,
        note: RefinementNote = RefinementNote.NOT_ATTEMPTED,
        ran: bool = False,
        geometric_only: bool = False,
        component_size: int = 0,
        target_depth_m: float = _NAN,
        threshold_m: float = _NAN,
        clearance_m: float = _NAN,
        clear_range_m: float = _NAN,
        bound_depth_m: float = _NAN,
    ) -> VerifiedGoal:
        u, v = candidate.pixel_uv
        logger.debug("verifier: rejected pixel (%.1f, %.1f): %s", u, v, reason.value)
        record = VerificationRecord(
            pixel_uv=(u, v),
            refined_uv=None,
            pixel_shift_px=_NAN,
            refinement_ran=ran,
            refinement_note=note,
            geometric_only=geometric_only,
            component_size_px=component_size,
            target_depth_m=float(target_depth_m),
            obstacle_threshold_m=float(threshold_m),
            ray_clearance_m=float(clearance_m),
            refined_depth_m=_NAN,
            bearing_rad=_NAN,
            gating_factor=_NAN,
            range_m=_NAN,
            rejection=reason,
            clear_range_m=float(clear_range_m),
            bound_depth_m=float(bound_depth_m),
        )
        return VerifiedGoal(goal_world=None, accepted=False, record=record)


# -- the target's surface, unread holes and the clear part of a ray ------------------------------


class _SurfaceRegion:
    """The target's surface inside a window of the image (see :mod:`planning.verifier_config`),
    grown on first use (the common case -- features, a target beyond the near field -- never
    needs it).

    ``mask`` is a boolean array over rows ``[r0, r1)`` and columns ``[c0, c1)`` of the image.
    """

    def __init__(self, depth, row, col, jump_ratio, margin_m, window) -> None:
        self.window = window
        self._args = (depth, row, col, jump_ratio, margin_m)
        self._mask: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        if self._mask is None:
            depth, row, col, jump_ratio, margin_m = self._args
            wr0, wr1, wc0, wc1 = self.window
            self._mask = surface_region(depth[wr0:wr1, wc0:wc1], row - wr0, col - wc0, jump_ratio, margin_m)
        return self._mask

    @classmethod
    def grow(cls, depth, row, col, jump_ratio, margin_m, roi, roi_px) -> "_SurfaceRegion":
        """The surface of (row, col) inside the ROI grown by ``roi_px`` on every side (beyond
        the window nothing is exempt from the near field: conservative)."""
        h, w = depth.shape
        r0, r1, c0, c1 = roi
        window = (max(0, r0 - roi_px), min(h, r1 + roi_px), max(0, c0 - roi_px), min(w, c1 + roi_px))
        return cls(depth, row, col, jump_ratio, margin_m, window)

    def crop(self, box: tuple[int, int, int, int]) -> np.ndarray:
        """The mask over ``box`` (inside the window)."""
        r0, r1, c0, c1 = box
        wr0, _, wc0, _ = self.window
        return self.mask[r0 - wr0 : r1 - wr0, c0 - wc0 : c1 - wc0].copy()

    def contains(self, row: int, col: int) -> bool:
        wr0, wr1, wc0, wc1 = self.window
        return wr0 <= row < wr1 and wc0 <= col < wc1 and bool(self.mask[row - wr0, col - wc0])


def surface_region(depth: np.ndarray, row: int, col: int, jump_ratio: float, band_m: float) -> np.ndarray:
    """Pixels depth-continuous with ``(row, col)``: the target's surface.

    4-connected region grown from the seed through neighbours whose depths differ by at most
    ``jump_ratio`` of the smaller one (``|ln z_a - ln z_b| <= ln(1 + jump_ratio)``), restricted to
    readings within ``band_m`` of the seed's depth. Pixels without a reading never join.

    Parameters
    ----------
    depth : array, shape (H, W), z-depth in metres (0, NaN, inf: no reading)
    row, col : int, the seed pixel (must have a reading)
    jump_ratio : float, > 0
    band_m : float, >= 0 (inf: no band)

    Returns
    -------
    array, shape (H, W), bool
    """
    z = np.asarray(depth, dtype=np.float32)
    d = float(z[row, col])
    if not (math.isfinite(d) and d > 0.0):
        raise ValueError(f"surface_region: seed ({row}, {col}) has no reading ({d})")
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(z) & (z > 0) & (np.abs(z - d) <= band_m)
        logz = np.where(ok, np.log(np.where(ok, z, 1.0)), np.float32(-1e4)).astype(np.float32)
    h, w = z.shape
    mask = np.zeros((h + 2, w + 2), np.uint8)
    tol = float(np.log1p(jump_ratio))
    flags = 4 | cv2.FLOODFILL_MASK_ONLY | (1 << 8)
    cv2.floodFill(logz, mask, (int(col), int(row)), 0, (tol,), (tol,), flags)
    return mask[1:-1, 1:-1].astype(bool)


@dataclass(frozen=True)
class _ObstacleView:
    """The depth image as the obstacle rule sees it for one reference depth: readings closer
    than ``threshold_m`` are obstacles, except the target's surface (set to NaN here)."""

    depth_m: np.ndarray
    threshold_m: float
    z_min: float | None
    exempted: bool = False  #: part of the target's surface was taken out of the near field

    @classmethod
    def at(cls, depth: np.ndarray, surface: _SurfaceRegion, d_m: float, cfg: VerifierConfig) -> "_ObstacleView":
        d_ref = min(d_m, cfg.d_max_m)
        threshold = cfg.obstacle_threshold_m(d_ref)
        view = depth
        exempted = False
        if cfg.obstacle_depth_m > d_ref - cfg.foreground_margin_m:
            # The near-field part of the rule reaches the target's depth band: exempt its surface.
            wr0, wr1, wc0, wc1 = surface.window
            with np.errstate(invalid="ignore"):
                exempt = surface.mask & (depth[wr0:wr1, wc0:wc1] >= d_ref - cfg.foreground_margin_m)
            if exempt.any():
                view = depth.copy()
                view[wr0:wr1, wc0:wc1][exempt] = np.nan
                exempted = True
        return cls(view, threshold, _nearest_obstacle_depth(view, threshold), exempted)

    def gather(self, camera: PinholeCamera, box, clearance_m: float) -> "_Obstacles":
        return _gather_obstacles(self.depth_m, camera, box, self.threshold_m, self.z_min, clearance_m)


def _hole_bound_depth(depth: np.ndarray, roi, row: int, col: int) -> float | None:
    """Smallest reading on the border of the no-reading region containing (row, col) inside the
    ROI (4-connected), metres; None when that border has no reading inside the ROI."""
    r0, r1, c0, c1 = roi
    z = depth[r0:r1, c0:c1]
    valid = cv2.inRange(z, _TINY_DEPTH, _MAX_DEPTH)  # 255 where a reading
    hole = cv2.bitwise_not(valid)
    _, labels = cv2.connectedComponents(hole, connectivity=4)
    comp = (labels == labels[row - r0, col - c0]).astype(np.uint8)
    ring = cv2.dilate(comp, _CROSS_3) & (valid != 0) & (comp == 0)
    if not ring.any():
        return None
    return float(z[ring.astype(bool)].min())


def _clear_range_z(
    depth: np.ndarray, camera: PinholeCamera, u: float, v: float, limit_z: float, clearance_m: float, surface_z: float
) -> float:
    """Z-depth up to which the ray through (u, v) keeps ``clearance_m`` from every reading.

    Every reading closer than ``limit_z + clearance_m`` whose clearance disc reaches the pixel is
    back-projected; the ray enters the ball of radius r around point ``Y`` at ray distance
    ``a - sqrt(r^2 - q^2)`` (``a`` along the ray, ``q`` off it). ``surface_z`` (finite for an
    unread pixel) adds the assumed surface on the ray itself. Returns ``min(limit_z, entry z)``;
    0 when the camera is within r of a reading on the ray.
    """
    threshold = float(limit_z) + clearance_m + 1e-6
    z_min = _nearest_obstacle_depth(depth, threshold)
    pts = _gather_obstacles(depth, camera, _pixel_box(u, v), threshold, z_min, clearance_m).points
    dvec = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
    dvec /= math.sqrt(float(dvec @ dvec))
    entry = math.inf
    if len(pts):
        along = pts @ dvec
        q2 = np.einsum("ij,ij->i", pts, pts) - along * along
        hit = q2 < clearance_m * clearance_m
        if hit.any():
            entry = float(np.min(along[hit] - np.sqrt(clearance_m * clearance_m - q2[hit])))
    if math.isfinite(surface_z):
        entry = min(entry, surface_z / dvec[2] - clearance_m)
    # One micron short of the ball's surface, so the goal clears every point by r after rounding.
    return float(min(limit_z, max(entry - _CLEAR_RANGE_MARGIN_M, 0.0) * dvec[2]))


def _any_valid(depth: np.ndarray) -> bool:
    """True when some pixel has a reading (finite, > 0)."""
    if depth.size == 0:
        return False
    return cv2.countNonZero(cv2.inRange(np.ascontiguousarray(depth), _TINY_DEPTH, _MAX_DEPTH)) > 0
