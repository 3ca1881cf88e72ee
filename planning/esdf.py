"""Local Euclidean signed distance field built from depth frames (a :class:`DistanceField`).

Pipeline of one :meth:`EsdfMap.integrate` call, and what each stage uses:

1. **Recentre** the rolling window on the vehicle (numpy slice copies, whole voxels on the
   global lattice ``floor(p / voxel_m)``: no resampling, so obstacles never smear).
2. **Occupancy** (:mod:`planning.esdf_occupancy`): Open3D back-projects the depth image into
   world points (``PointCloud.create_from_depth_image``), numpy bins them into hit voxels and
   projects the obstacle voxels of the frustum into the image for free-space clearing, then a
   log-odds update. Output: the voxels whose obstacle state flipped.
3. **Distance** (:mod:`planning.esdf_edt`, numpy): Fast-Planner's bounding-box idea. The box
   of the flipped voxels, grown by the clamp ``K = max_distance_m``, is the only region whose
   distances can change; it is rewritten from an exact truncated EDT computed on the box grown
   by ``2 K`` (every obstacle within ``K`` of a rewritten voxel is inside that block), so the
   field stays exactly the full-grid EDT (clamped) after every frame. Changes far apart are
   split into several boxes (clusters of ``K``-sized cells) when that is cheaper than their
   hull, and the inside transform runs only around obstacle voxels with no free face
   neighbour. scipy's ``distance_transform_edt`` computes the same field on the whole grid;
   ``experiments/bench_esdf.py`` compares the two.

Field convention (Fast-Planner's): for a free voxel, the distance between its centre and the
nearest obstacle voxel centre; for an obstacle voxel, minus the distance to the nearest free
voxel centre plus one voxel (so the outermost obstacle voxels read 0 and the zero level sits
on the voxel centres that hold the measured surface). Values are clamped to
``[-max_inside_distance_m, max_distance_m]``. Queries interpolate trilinearly between voxel
centres.

Grid edges and outside: coordinates are clamped to the box of voxel centres (within half a voxel
of the faces and beyond). With ``unknown_policy="free"`` the field is extended as a constant
along the outward normal (gradient component 0). With ``"occupied"`` space outside the window is
an obstacle: the transform treats the faces as bordering obstacles, and beyond the centre box
the value decreases at unit slope, ``d(q) = d(c) - |q - c|`` (``c`` the clamped point), with
the matching gradient.

Unknown space (default ``EsdfConfig.unknown_policy="occupied"``; ``docs/esdf_unknown_space.md``):
a voxel is *unknown* until a depth reading hits it, a ray passes through it, or the vehicle's
body sphere covers it; unknown voxels and space outside the window are obstacles for
:meth:`EsdfMap.query` and :meth:`EsdfMap.is_free`, so a plan never enters space the camera has
not seen free. A pixel without a reading (sky, glass, dark surfaces, beyond range) clears its
ray only up to ``min(no_reading_clear_m, nearest reading on its row and column) -
clear_margin_m`` and never clears an observed obstacle, so a hole in a wall does not become a
passage while open sky still clears the space the vehicle flies through. The unknown voxels
within ``body_clear_radius_m`` of the vehicle that the frame's camera cannot see are marked free
at every frame (it is there; what the camera looks at is left to the camera).

Knownness queries (for guide searches, frontier exploration and the verifier), world metres:

- :meth:`EsdfMap.known` ``(n, 3) -> bool (n,)``: the voxel holding the point was observed.
- :meth:`EsdfMap.observed_free` ``(n, 3) -> bool (n,)``: observed and not occupied.
- :meth:`EsdfMap.logodds` ``(n, 3) -> float32 (n,)``: the voxel's log-odds, NaN where unknown.
- :attr:`EsdfMap.known_grid`, :attr:`EsdfMap.occupied_grid`: bool (nx, ny, nz) grids (voxel
  centres from :meth:`EsdfMap.voxel_centers`).
- :meth:`EsdfMap.frontier_points` ``-> (m, 3)``: observed-free voxels next to unknown ones.
- :meth:`EsdfMap.mark_free_sphere`: mark unknown voxels in a sphere free (the vehicle's body).

Knownness is complete under the default policy only: with ``unknown_policy="free"`` clearing
projects only obstacle voxels (the optimistic map's shortcut), so free space that rays pass
through is never marked observed and :meth:`EsdfMap.known` is true mostly on obstacles.

The map assumes nothing about which world axis is up.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from planning.camera import CameraError, PinholeCamera
from planning.esdf_config import EsdfConfig
from planning.esdf_edt import truncated_squared_edt
from planning.esdf_occupancy import IndexBox, RollingOccupancy, shift_array
from planning.frames import check_transform

__all__ = ["EsdfMap", "EsdfUpdate", "EsdfError", "DistanceSlice"]

log = logging.getLogger(__name__)


class EsdfError(ValueError):
    """Bad input to the ESDF map (wrong shape, non-finite points, wrong camera type)."""


@dataclass(frozen=True)
class EsdfUpdate:
    """Statistics of one :meth:`EsdfMap.integrate` call.

    Attributes
    ----------
    n_points : back-projected depth points within range (after the stride)
    n_hit_voxels, n_miss_voxels : distinct voxels hit / seen through in this frame
    n_changed_voxels : voxels whose obstacle state flipped
    changed_box_min_m, changed_box_max_m : world AABB (voxel faces, metres) of the flipped
        voxels, or None when nothing flipped
    shift_voxels : (3,) whole voxels the window moved before this frame
    esdf_voxels : voxel distances rewritten (the frame's boxes and the shift slabs; a voxel in
        two overlapping boxes counts twice)
    shift_ms, backproject_ms, occupancy_ms, esdf_ms, total_ms : wall time of each stage
        (shift_ms includes the distance update of the shift slabs)
    """

    n_points: int
    n_hit_voxels: int
    n_miss_voxels: int
    n_changed_voxels: int
    changed_box_min_m: tuple[float, float, float] | None
    changed_box_max_m: tuple[float, float, float] | None
    shift_voxels: tuple[int, int, int]
    esdf_voxels: int
    shift_ms: float
    backproject_ms: float
    occupancy_ms: float
    esdf_ms: float
    total_ms: float


@dataclass(frozen=True)
class DistanceSlice:
    """One horizontal layer of the field, for pictures.

    Attributes
    ----------
    z_m : world z of the layer (a voxel-centre height), metres
    x_m : shape (nx,), world x of the voxel centres, metres
    y_m : shape (ny,), world y of the voxel centres, metres
    distance_m : shape (nx, ny), signed distance at the voxel centres, metres
    """

    z_m: float
    x_m: np.ndarray
    y_m: np.ndarray
    distance_m: np.ndarray


# Corner offsets of a trilinear cell, ordered (dx, dy, dz) as bits 4, 2, 1.
_CORNERS = np.array([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], dtype=np.int64)


class EsdfMap:
    """Rolling occupancy + incrementally updated, exact, clamped ESDF.

    Build once, integrate every depth frame, query at any rate::

        esdf = EsdfMap(EsdfConfig())
        stats = esdf.integrate(depth_m, camera, T_world_cam)
        d, grad = esdf.query(points)          # (n,), (n, 3)
    """

    def __init__(self, config: EsdfConfig | None = None) -> None:
        self.config = config if config is not None else EsdfConfig()
        if not isinstance(self.config, EsdfConfig):
            raise EsdfError(f"config must be an EsdfConfig, got {type(self.config).__name__}")
        cfg = self.config
        self._occ = RollingOccupancy(cfg)
        self.shape = self._occ.shape
        self._shape_arr = np.asarray(self.shape, dtype=np.int64)
        self._strides = np.array([self.shape[1] * self.shape[2], self.shape[2], 1], dtype=np.int64)
        self._corner_offsets = _CORNERS @ self._strides
        self._hi_centre = (self._shape_arr - 1).astype(float)
        self._cell_max = self._shape_arr - 2
        self._unknown_solid = cfg.unknown_policy == "occupied"
        self._k_out = cfg.max_distance_voxels
        self._k_in = cfg.max_inside_voxels
        v = cfg.voxel_m
        k2 = np.arange(self._k_out**2 + 2, dtype=float)
        self._lut_out = np.minimum(np.sqrt(k2) * v, cfg.max_distance_m).astype(np.float32)
        k2 = np.arange(self._k_in**2 + 2, dtype=float)
        lut_in = -np.minimum((np.sqrt(k2) - 1.0) * v, cfg.max_inside_distance_m)
        lut_in[0] = 0.0
        self._lut_in = lut_in.astype(np.float32)
        self._distance = np.empty(self.shape, dtype=np.float32)
        self._update_box(((0, 0, 0), self.shape))

    # -- window -----------------------------------------------------------------------------
    @property
    def voxel_m(self) -> float:
        return self.config.voxel_m

    @property
    def origin_index(self) -> np.ndarray:
        """Global lattice index (3,) int of local voxel (0, 0, 0)."""
        return self._occ.origin_index.copy()

    @property
    def bounds_world(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo (3,), hi (3,))``: world AABB of the window (outer voxel faces), metres."""
        lo = self._occ.origin_index * self.voxel_m
        return lo.astype(float), (lo + self._shape_arr * self.voxel_m).astype(float)

    @property
    def distance_grid(self) -> np.ndarray:
        """Read-only view of the signed distance at voxel centres, (nx, ny, nz), metres."""
        view = self._distance.view()
        view.flags.writeable = False
        return view

    def voxel_centers(self) -> np.ndarray:
        """World centres of all voxels, shape (nx, ny, nz, 3), metres."""
        idx = np.stack(np.meshgrid(*(np.arange(n) for n in self.shape), indexing="ij"), axis=-1)
        return (idx + self._occ.origin_index + 0.5) * self.voxel_m

    def reset(self) -> None:
        """Forget every observation (the window stays where it is)."""
        self._occ.reset()
        self._update_box(((0, 0, 0), self.shape))

    def recenter(self, center_world) -> tuple[int, int, int]:
        """Move the window so ``center_world`` (3,) metres lies in voxel ``shape // 2``.

        Returns the shift in whole voxels. Overlapping content is kept voxel for voxel; entering
        voxels are unknown; distances near the entering and leaving faces are recomputed.
        """
        return self._recenter(center_world)[0]

    def _recenter(self, center_world) -> tuple[tuple[int, int, int], int]:
        """:meth:`recenter`, also returning how many voxel distances were rewritten."""
        center = np.asarray(center_world, dtype=float)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise EsdfError(f"center_world must be a finite array of shape (3,), got {center!r}")
        shift, boxes = self._occ.shift_to(self._occ.origin_for_center(center))
        n_rewritten = 0
        if shift.any():
            fill = -self.config.max_inside_distance_m if self._unknown_solid else self.config.max_distance_m
            self._distance = shift_array(self._distance, shift, np.float32(fill))
            for box in boxes:
                n_rewritten += self._update_box(box)
        return tuple(int(s) for s in shift), n_rewritten

    # -- integration ------------------------------------------------------------------------
    def integrate(
        self, depth_m, camera: PinholeCamera, T_world_cam, center_world=None, body_world=None, body_margin_m: float = 0.0
    ) -> EsdfUpdate:
        """Fuse one depth frame and update the field where it changed.

        Parameters
        ----------
        depth_m : array, shape (camera.height, camera.width), z-depth in metres, a float dtype
            (float32 preferred; :meth:`PinholeCamera.check_depth`: an integer frame is raw
            counts and a frame mostly beyond 65.5 m is millimetres, both ``EsdfError``).
            0, NaN, inf, negative values and readings below ``min_range_m`` are no
            reading and ignored; readings beyond ``max_range_m`` only clear free space.
        camera : PinholeCamera of the depth image
        T_world_cam : (4, 4) rigid transform camera optical -> world. Checked with
            :func:`planning.frames.check_transform` (raises ``FrameError`` for NaN / inf,
            a non-orthonormal or reflecting rotation block, or a bad last row).
        center_world : (3,) metres, centre of the rolling window; default the camera position.
        body_world : (3,) metres, the vehicle's position: the unknown voxels within
            ``body_clear_radius_m`` of it that this frame's camera cannot see (see
            ``EsdfConfig.body_clear_in_view``) become free after the frame. Default ``center_world``
            when given (the pilot centres the window on the vehicle), else the camera position.
        body_margin_m : metres >= 0 added to ``body_clear_radius_m`` for this frame: the
            planner's tracking margin (``Planner.tracking_margin_m``), by which it grows the
            clearance it keeps. The sphere exists so that the planner can move where the camera
            cannot see (below and beside a level camera); with the clearance grown by the
            margin and the sphere not, the vehicle could not leave it (gusts outdoors). 0 under
            perfect tracking, so an ideal world's map is unchanged.

        Returns
        -------
        EsdfUpdate with counts, the changed box and per-stage timings.
        """
        t0 = time.perf_counter()
        if not isinstance(camera, PinholeCamera):
            raise EsdfError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
        T = check_transform(T_world_cam, "T_world_cam")
        depth = np.asarray(depth_m)
        if depth.ndim != 2:
            raise EsdfError(f"depth_m must be a 2-D (height, width) array, got shape {depth.shape}")
        camera.check_image(depth, "depth_m")
        try:
            depth = camera.check_depth(depth, "depth_m")  # float metres: counts and millimetres refused
        except CameraError as exc:
            raise EsdfError(str(exc)) from None
        center = T[:3, 3] if center_world is None else center_world
        if body_world is not None:
            body_world = np.asarray(body_world, dtype=float)
            if body_world.shape != (3,) or not np.all(np.isfinite(body_world)):
                raise EsdfError(f"body_world must be a finite array of shape (3,), got {body_world!r}")
        if not (isinstance(body_margin_m, (int, float)) and math.isfinite(body_margin_m) and body_margin_m >= 0):
            raise EsdfError(f"body_margin_m must be a finite number >= 0, got {body_margin_m!r}")
        t_shift = time.perf_counter()
        shift, n_esdf = self._recenter(center)  # validates center_world
        body = np.asarray(center, dtype=float) if body_world is None else body_world
        t_occ = time.perf_counter()
        delta = self._occ.integrate(depth, camera, T, body_world=body, body_margin_m=float(body_margin_m))
        t_esdf = time.perf_counter()
        if delta.n_points == 0:
            log.debug("depth frame had no reading in [%.2f, %.2f) m", self.config.min_range_m, self.config.max_range_m)
        n_box, box_min, box_max = self._apply_flipped(delta.flipped)
        n_esdf += n_box
        t_end = time.perf_counter()
        return EsdfUpdate(
            n_points=delta.n_points,
            n_hit_voxels=delta.n_hit_voxels,
            n_miss_voxels=delta.n_miss_voxels,
            n_changed_voxels=int(delta.flipped.size),
            changed_box_min_m=box_min,
            changed_box_max_m=box_max,
            shift_voxels=shift,
            esdf_voxels=n_esdf,
            shift_ms=(t_occ - t_shift) * 1e3,
            backproject_ms=delta.backproject_ms,
            occupancy_ms=delta.update_ms,
            esdf_ms=(t_end - t_esdf) * 1e3,
            total_ms=(t_end - t0) * 1e3,
        )

    def _apply_flipped(self, flipped: np.ndarray):
        """Rewrite the distances around flipped voxels (k,) flat; returns (voxels rewritten,
        world box min, world box max) with None boxes when nothing flipped."""
        if not flipped.size:
            return 0, None, None
        idx = np.stack(np.unravel_index(flipped, self.shape), axis=-1)
        lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
        n = 0
        for box in self._cluster_boxes(idx):
            n += self._update_box(box)
        box_min = tuple(float(v) for v in (lo + self._occ.origin_index) * self.voxel_m)
        box_max = tuple(float(v) for v in (hi + self._occ.origin_index) * self.voxel_m)
        return n, box_min, box_max

    def mark_free_sphere(self, center_world, radius_m: float) -> int:
        """Mark the *unknown* voxels whose centre is within ``radius_m`` metres of
        ``center_world`` (3,) world metres free, and update the field. Observed voxels (hit or
        seen through) are left alone. For the vehicle's own body, e.g. before the first frame;
        :meth:`integrate` already does it at ``body_world`` with ``body_clear_radius_m``.

        Returns the number of voxels whose obstacle state flipped.
        """
        c = np.asarray(center_world, dtype=float)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise EsdfError(f"center_world must be a finite array of shape (3,), got {center_world!r}")
        if not (np.isfinite(radius_m) and radius_m >= 0):
            raise EsdfError(f"radius_m must be a finite number >= 0, got {radius_m!r}")
        flipped = self._occ.mark_free_sphere(c, float(radius_m))
        self._apply_flipped(flipped)
        return int(flipped.size)

    def _block_cost(self, lo: np.ndarray, hi: np.ndarray) -> int:
        """Voxels in the outside-transform block of a changed box (its cost, roughly)."""
        k2 = 2 * self._k_out
        return int(np.prod(np.minimum(hi + k2, self._shape_arr) - np.maximum(lo - k2, 0)))

    def _cluster_boxes(self, idx: np.ndarray) -> list[IndexBox]:
        """Split flipped voxels (k, 3) into boxes that are cheaper to update than their hull.

        A frame's changes are often a few small clusters far apart (new surfaces at the edges
        of the view); one bounding box would span the empty space between them. Voxels are
        grouped by connected cells of ``K`` voxels (26-neighbourhood), then boxes are merged
        greedily while the merged block costs no more than the two apart. Any partition is
        exact: each box rewrites exactly the voxels within ``K`` of its changes.
        """
        lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
        if len(idx) < 2 or np.all(hi - lo <= 2 * self._k_out):
            return [(tuple(int(v) for v in lo), tuple(int(v) for v in hi))]
        cell = idx // self._k_out
        coarse = np.zeros(tuple(self._shape_arr // self._k_out + 1), dtype=bool)
        coarse[tuple(cell.T)] = True
        labels, n = ndi.label(coarse, structure=np.ones((3, 3, 3), dtype=bool))
        if n == 1:
            return [(tuple(int(v) for v in lo), tuple(int(v) for v in hi))]
        lab = labels[tuple(cell.T)] - 1
        los = np.full((n, 3), np.iinfo(np.int64).max, dtype=np.int64)
        his = np.full((n, 3), -1, dtype=np.int64)
        np.minimum.at(los, lab, idx)
        np.maximum.at(his, lab, idx + 1)
        boxes = [(los[i], his[i]) for i in range(n)]
        merged = True
        while merged and len(boxes) > 1:
            merged = False
            for i in range(len(boxes)):
                for j in range(i + 1, len(boxes)):
                    (a_lo, a_hi), (b_lo, b_hi) = boxes[i], boxes[j]
                    u_lo, u_hi = np.minimum(a_lo, b_lo), np.maximum(a_hi, b_hi)
                    if self._block_cost(u_lo, u_hi) <= self._block_cost(a_lo, a_hi) + self._block_cost(b_lo, b_hi):
                        boxes[i] = (u_lo, u_hi)
                        del boxes[j]
                        merged = True
                        break
                if merged:
                    break
        return [(tuple(int(v) for v in a), tuple(int(v) for v in b)) for a, b in boxes]

    def _update_box(self, box: IndexBox) -> int:
        """Rewrite the distance of every voxel within ``K`` of ``box``; returns how many.

        ``box`` is a half-open local index box of voxels whose obstacle state changed. The
        outside transform runs on the box grown by ``2 K`` (clipped to the grid). Obstacle
        voxels with a free 6-neighbour are exactly one voxel from free space and read 0 (the
        outside lookup already gives that); only the interior ones (all six neighbours solid)
        need the inside transform, run on their bounding box grown by the inside clamp.
        """
        shape = self._shape_arr
        lo, hi = np.asarray(box[0], dtype=np.int64), np.asarray(box[1], dtype=np.int64)
        w_lo, w_hi = np.maximum(lo - self._k_out, 0), np.minimum(hi + self._k_out, shape)
        w = tuple(slice(int(a), int(b)) for a, b in zip(w_lo, w_hi))
        solid = self._occ.solid
        d2_out = self._block_edt(solid, w_lo, w_hi, self._k_out, sites_are_solid=True)
        np.take(self._lut_out, d2_out, out=self._distance[w], mode="clip")
        interior = self._interior(solid, w_lo, w_hi)
        if interior is not None:
            # bounding box of the interior voxels from three axis projections (no index list:
            # under the occupied policy the unseen interior is most of the block)
            spans = [np.flatnonzero(interior.any(axis=other)) for other in ((1, 2), (0, 2), (0, 1))]
            r_lo = w_lo + np.array([sp[0] for sp in spans])
            r_hi = w_lo + np.array([sp[-1] + 1 for sp in spans])
            d2_in = self._block_edt(solid, r_lo, r_hi, self._k_in, sites_are_solid=False)
            r = tuple(slice(int(a), int(b)) for a, b in zip(r_lo - w_lo, r_hi - w_lo))
            inner = interior[r]
            region = self._distance[tuple(slice(int(a), int(b)) for a, b in zip(r_lo, r_hi))]
            region[inner] = self._lut_in[d2_in[inner]]
        return int(np.prod(w_hi - w_lo))

    def _interior(self, solid: np.ndarray, w_lo: np.ndarray, w_hi: np.ndarray) -> np.ndarray | None:
        """Bool mask over ``[w_lo, w_hi)`` of solid voxels whose six face neighbours are solid.

        Space outside the window takes the unknown policy. None when there is no such voxel.
        """
        shape = self._shape_arr
        e_lo, e_hi = np.maximum(w_lo - 1, 0), np.minimum(w_hi + 1, shape)
        e = solid[tuple(slice(int(a), int(b)) for a, b in zip(e_lo, e_hi))]
        pad = [(int(a == 0), int(b == n)) for a, b, n in zip(w_lo, w_hi, shape)]
        if any(p != (0, 0) for p in pad):
            e = np.pad(e, pad, mode="constant", constant_values=self._unknown_solid)
        core = (slice(1, -1),) * 3
        out = e[core].copy()
        if not out.any():
            return None
        for axis in range(3):
            lo_s, hi_s = list(core), list(core)
            lo_s[axis], hi_s[axis] = slice(None, -2), slice(2, None)
            out &= e[tuple(lo_s)]
            out &= e[tuple(hi_s)]
        return out if out.any() else None

    def _block_edt(self, solid, w_lo, w_hi, k: int, sites_are_solid: bool) -> np.ndarray:
        """Truncated squared EDT on the write region ``[w_lo, w_hi)``, from a block grown by k.

        Sites are the solid voxels (outside distance) or the free ones (inside distance).
        Faces of the block on the grid boundary are padded with one layer of the state that
        the unknown policy gives to space outside the window.
        """
        shape = self._shape_arr
        b_lo, b_hi = np.maximum(w_lo - k, 0), np.minimum(w_hi + k, shape)
        block = solid[tuple(slice(int(a), int(b)) for a, b in zip(b_lo, b_hi))]
        sites = block if sites_are_solid else ~block
        outside_is_site = self._unknown_solid if sites_are_solid else not self._unknown_solid
        pad = None
        if outside_is_site:
            pad = [(int(a == 0), int(b == n)) for a, b, n in zip(b_lo, b_hi, shape)]
            if any(p != (0, 0) for p in pad):
                sites = np.pad(sites, pad, mode="constant", constant_values=True)
            else:
                pad = None
        off_lo = w_lo - b_lo
        if pad is not None:
            off_lo = off_lo + np.array([p[0] for p in pad])
        off_hi = off_lo + (w_hi - w_lo)
        if not sites.any():
            return np.full(tuple(w_hi - w_lo), k * k + 1, dtype=np.uint16)
        if sites.all():
            return np.zeros(tuple(w_hi - w_lo), dtype=np.uint8)
        return truncated_squared_edt(sites, k, region=(off_lo, off_hi))

    # -- queries ----------------------------------------------------------------------------
    def query(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance and its gradient at many points (trilinear between voxel centres).

        Parameters
        ----------
        points : array, shape (n, 3), metres, world frame

        Returns
        -------
        distance : shape (n,), metres, clamped to [-max_inside_distance_m, max_distance_m]
            (beyond the window with unknown as occupied it keeps decreasing, see module doc)
        gradient : shape (n, 3), 1/1 (metres per metre), derivative of the interpolant
            (piecewise constant across cells; zero where the field is clamped flat)
        """
        P = np.asarray(points, dtype=float)
        if P.ndim != 2 or P.shape[1] != 3:
            raise EsdfError(f"points must have shape (n, 3), got {P.shape}")
        if not np.isfinite(P).all():
            raise EsdfError("points contain NaN or inf")
        v = self.voxel_m
        c = P * (1.0 / v) - (self._occ.origin_index + 0.5)
        cc = np.clip(c, 0.0, self._hi_centre)
        i0 = np.minimum(cc.astype(np.int64), self._cell_max)
        f = cc - i0
        idx = (i0 @ self._strides)[:, None] + self._corner_offsets
        vals = self._distance.reshape(-1)[idx].astype(float).reshape(-1, 2, 2, 2)
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        dz = vals[..., 1] - vals[..., 0]  # (n, 2, 2) over (x, y)
        a = vals[..., 0] + dz * fz[:, None, None]  # interpolated in z, (n, 2, 2)
        ay = a[:, :, 1] - a[:, :, 0]  # (n, 2) over x
        b = a[:, :, 0] + ay * fy[:, None]  # (n, 2) over x
        bx = b[:, 1] - b[:, 0]
        dist = b[:, 0] + bx * fx
        dzy = dz[:, :, 0] + (dz[:, :, 1] - dz[:, :, 0]) * fy[:, None]  # (n, 2) over x
        grad = np.empty_like(P)
        grad[:, 0] = bx
        grad[:, 1] = ay[:, 0] + (ay[:, 1] - ay[:, 0]) * fx
        grad[:, 2] = dzy[:, 0] + (dzy[:, 1] - dzy[:, 0]) * fx
        grad *= 1.0 / v
        outside = c != cc
        if outside.any():
            grad[outside] = 0.0
            if self._unknown_solid:
                e = (c - cc) * v
                r = np.sqrt(np.einsum("ij,ij->i", e, e))
                out = r > 0
                dist[out] -= r[out]
                grad[out] -= e[out] / r[out, None]
        return dist, grad

    def is_free(self, points, margin_m: float = 0.0) -> np.ndarray:
        """True where the interpolated distance at ``points`` (n, 3) exceeds ``margin_m`` metres.

        Unknown space counts by the unknown policy.
        """
        dist, _ = self.query(points)
        return dist > margin_m

    # -- knownness --------------------------------------------------------------------------
    def _voxel_lookup(self, points) -> tuple[np.ndarray, np.ndarray]:
        """(flat local index (n,), inside-window mask (n,)) of the voxels holding ``points``."""
        P = np.asarray(points, dtype=float)
        if P.ndim != 2 or P.shape[1] != 3:
            raise EsdfError(f"points must have shape (n, 3), got {P.shape}")
        if not np.isfinite(P).all():
            raise EsdfError("points contain NaN or inf")
        idx = np.floor(P / self.voxel_m).astype(np.int64) - self._occ.origin_index
        inside = np.all((idx >= 0) & (idx < self._shape_arr), axis=1)
        flat = np.where(inside, np.clip(idx, 0, self._shape_arr - 1) @ self._strides, 0)
        return flat, inside

    def known(self, points) -> np.ndarray:
        """True where the voxel holding each point (n, 3) world metres has been observed: hit,
        passed through by a ray, or inside the vehicle's body sphere. False outside the window
        (forgotten or never seen). Returns bool (n,)."""
        flat, inside = self._voxel_lookup(points)
        return inside & self._occ.observed.reshape(-1)[flat]

    def observed_free(self, points) -> np.ndarray:
        """True where the voxel holding each point (n, 3) world metres is known and not
        occupied: space the camera has seen free (or the vehicle has been in). Returns bool (n,).

        Voxel-level (nearest voxel, no interpolation); for clearance use :meth:`query`.
        """
        flat, inside = self._voxel_lookup(points)
        occ = self._occ
        free = occ.observed.reshape(-1)[flat] & ~(occ.logodds.reshape(-1)[flat] > np.float32(self.config.occupied_logodds))
        return inside & free

    def logodds(self, points) -> np.ndarray:
        """Occupancy log-odds (float32 (n,)) of the voxel holding each point (n, 3), world
        metres; NaN where the voxel was never observed or lies outside the window. Negative =
        seen free (each miss adds ``miss_logodds``), above ``occupied_logodds`` = obstacle."""
        flat, inside = self._voxel_lookup(points)
        occ = self._occ
        seen = inside & occ.observed.reshape(-1)[flat]
        return np.where(seen, occ.logodds.reshape(-1)[flat], np.float32(np.nan)).astype(np.float32)

    @property
    def known_grid(self) -> np.ndarray:
        """Read-only bool view (nx, ny, nz): observed voxels (see :meth:`known`)."""
        view = self._occ.observed.view()
        view.flags.writeable = False
        return view  # a view of the current array: fetch it again after the window moves

    @property
    def occupied_grid(self) -> np.ndarray:
        """Bool (nx, ny, nz), a new array: observed voxels whose log-odds say obstacle."""
        return self._occ.observed & (self._occ.logodds > np.float32(self.config.occupied_logodds))

    def frontier_points(self, axes: tuple[int, ...] = (0, 1, 2)) -> np.ndarray:
        """World centres (m, 3), metres, of frontier voxels: observed free voxels with at least
        one unknown face neighbour inside the window (the edge of what has been seen free,
        where exploration leads). Faces on the window boundary do not count.

        axes : the grid axes (0 = x, 1 = y, 2 = z) whose faces count. ``(0, 1)`` gives the ways
            on at a height: the unknown space over the vehicle's trail (the body sphere stops
            ``body_clear_above_m`` over it, and a level camera never sees straight up) borders
            every free voxel at the trail's top, a frontier no flight at that height leads to.
        """
        if not axes or any(a not in (0, 1, 2) for a in axes):
            raise EsdfError(f"axes must be a non-empty subset of (0, 1, 2), got {axes!r}")
        known = self._occ.observed
        free = known & ~(self._occ.logodds > np.float32(self.config.occupied_logodds))
        unknown = ~known
        touch = np.zeros(self.shape, dtype=bool)
        for axis in sorted(set(axes)):
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(None, -1), slice(1, None)
            touch[tuple(lo)] |= unknown[tuple(hi)]
            touch[tuple(hi)] |= unknown[tuple(lo)]
        return self._occ.centers_of(np.flatnonzero(free & touch))

    def occupied_points(self) -> np.ndarray:
        """World centres (m, 3), metres, of the observed obstacle voxels (for pictures)."""
        occ = self._occ.observed & (self._occ.logodds > np.float32(self.config.occupied_logodds))
        return self._occ.centers_of(np.flatnonzero(occ))

    def distance_slice(self, z_m: float) -> DistanceSlice:
        """The layer of voxel centres nearest world height ``z_m`` (clamped into the window)."""
        if not np.isfinite(z_m):
            raise EsdfError(f"z_m must be finite, got {z_m}")
        v = self.voxel_m
        o = self._occ.origin_index
        k = int(np.clip(np.floor(z_m / v) - o[2], 0, self.shape[2] - 1))
        x = (np.arange(self.shape[0]) + o[0] + 0.5) * v
        y = (np.arange(self.shape[1]) + o[1] + 0.5) * v
        return DistanceSlice(float((k + o[2] + 0.5) * v), x, y, self._distance[:, :, k].copy())
