"""Rolling log-odds occupancy grid fed by depth frames (the input of the ESDF).

The grid is a window of ``(nx, ny, nz)`` voxels on the global lattice
``index = floor(p_world / voxel_m)``; ``origin_index`` is the global index of local voxel
``(0, 0, 0)``. Arrays are indexed ``[ix, iy, iz]`` (C order, flat index
``(ix * ny + iy) * nz + iz``), world axes, whatever the world frame is (nothing here assumes z up).

One frame does, in order (the docstring of :meth:`RollingOccupancy.integrate` has details):

1. **Hits** -- Open3D back-projects the (strided) depth image straight into the world frame
   (``o3d.t.geometry.PointCloud.create_from_depth_image`` with the world-to-camera extrinsic;
   C++, multi-threaded); numpy bins the points into voxels with a scatter into a scratch mask
   (no sort). The voxels up to ``surface_thickness_m`` behind each hit voxel along its ray are
   hit too.
2. **Misses (free-space clearing)** -- projective: every voxel that could still change the
   field (the obstacle voxels, plus the unknown ones when unknown counts as occupied) inside the
   frustum's bounding box is projected into the full-resolution image (numpy, vectorized); it is
   passed through when its z-depth is below the pixel's *reach* (:func:`free_reach`): the
   reading minus ``clear_margin_m`` (finite readings beyond ``max_range_m`` clear up to
   ``max_range_m``); for a pixel without a reading (0 / NaN / inf / negative / below
   ``min_range_m``) ``min(no_reading_clear_m, nearest reading on its row and column) -
   clear_margin_m``, and such a pixel never clears an occupied voxel. A hit in the same frame
   wins.
3. **Log-odds update** on the touched voxels only, and the list of voxels whose obstacle state
   (the mask the distance transform sees) flipped.
4. **Body sphere** -- the unknown voxels within ``body_clear_radius_m`` of the vehicle, and
   at most ``body_clear_above_m`` above it, that the frame's camera cannot see (below, behind
   or beside its view) are marked free
   (:meth:`RollingOccupancy.mark_free_sphere`; voxblox's clear sphere, minus the view).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from planning.camera import PinholeCamera
from planning.esdf_config import EsdfConfig
from planning.frames import invert_transform

__all__ = ["RollingOccupancy", "OccupancyDelta", "IndexBox", "free_reach"]

log = logging.getLogger(__name__)

#: Edge, in voxels, of the blocks culled against the view frustum before clearing.
_BLOCK = 8

#: Half-open box of local voxel indices: ``(lo (3,), hi (3,))`` with ``lo <= i < hi``.
IndexBox = tuple[tuple[int, int, int], tuple[int, int, int]]


@dataclass(frozen=True)
class OccupancyDelta:
    """What one frame did to the occupancy grid.

    Attributes
    ----------
    flipped : int64 array, shape (k,), flat local indices whose obstacle state flipped
    n_points : back-projected points within range (after the stride)
    n_hit_voxels, n_miss_voxels : distinct voxels hit / passed through in this frame
    backproject_ms, update_ms : wall time of the Open3D back-projection and of the rest
    """

    flipped: np.ndarray
    n_points: int
    n_hit_voxels: int
    n_miss_voxels: int
    backproject_ms: float
    update_ms: float


def _nearest_reading_along(d: np.ndarray, valid: np.ndarray, axis: int, reverse: bool) -> np.ndarray:
    """Per pixel, the first valid value of ``d`` met scanning along ``axis`` (the pixel itself
    included), toward lower indices or, with ``reverse``, higher ones; inf where none."""
    n = d.shape[axis]
    shape = [1, 1]
    shape[axis] = n
    pos = np.arange(n, dtype=np.int32).reshape(shape)
    if reverse:
        idx = np.where(valid, pos, np.int32(n))
        last = np.flip(np.minimum.accumulate(np.flip(idx, axis=axis), axis=axis), axis=axis)
        found = last < n
    else:
        idx = np.where(valid, pos, np.int32(-1))
        last = np.maximum.accumulate(idx, axis=axis)
        found = last >= 0
    out = np.take_along_axis(d, np.clip(last, 0, n - 1), axis=axis)
    return np.where(found, out, np.float32(np.inf))


def free_reach(depth_m: np.ndarray, config: EsdfConfig) -> tuple[np.ndarray, np.ndarray]:
    """How far each pixel's ray may clear free space, and which pixels hold a reading.

    Parameters
    ----------
    depth_m : float32 array (h, w), z-depth in metres (0 / NaN / inf / negative / below
        ``min_range_m`` are no reading)
    config : the map's EsdfConfig (``min_range_m``, ``max_range_m``, ``clear_margin_m``,
        ``no_reading_clear_m``)

    Returns
    -------
    reach : float32 (h, w), z-depth in metres below which a voxel centre projecting to the pixel
        is passed through. A reading ``d``: ``min(d, max_range_m) - clear_margin_m``. No
        reading: ``min(no_reading_clear_m, r_nb) - clear_margin_m`` with ``r_nb`` the nearest of
        the first readings met scanning left, right, up and down from the pixel (each clipped to
        ``max_range_m``), so a hole never clears past the surface it is cut into. A pixel whose
        four scans meet no reading (and every pixel of a frame without any reading) clears
        nothing: nothing bounds it (a pane of glass filling the view). With
        ``no_reading_needs_below``, neither does one whose column holds no reading below it.
    valid : bool (h, w), True where the pixel holds a reading
    """
    cfg = config
    with np.errstate(invalid="ignore"):
        valid = (depth_m >= np.float32(cfg.min_range_m)) & (depth_m < np.inf)  # no NaN, inf, <= 0
    clipped = np.where(valid, np.minimum(depth_m, np.float32(cfg.max_range_m)), np.float32(np.inf)).astype(np.float32)
    margin = np.float32(cfg.clear_margin_m)
    reach = clipped - margin
    if valid.all():
        return reach, valid
    if cfg.no_reading_clear_m <= 0 or not valid.any():
        reach[~valid] = -np.inf  # off, or a blind frame (nothing bounds a hole): clear nothing
        return reach, valid
    nb = _nearest_reading_along(clipped, valid, 1, False)
    np.minimum(nb, _nearest_reading_along(clipped, valid, 1, True), out=nb)
    np.minimum(nb, _nearest_reading_along(clipped, valid, 0, False), out=nb)
    below = _nearest_reading_along(clipped, valid, 0, True)  # down the image: higher rows
    np.minimum(nb, below, out=nb)
    if cfg.no_reading_needs_below:
        nb[~np.isfinite(below)] = np.inf  # nothing read below: unbounded, clears nothing
    hole = ~valid
    # nb is inf where the scans met no reading: then nothing bounds the hole and it clears nothing
    reach[hole] = np.where(np.isfinite(nb[hole]), np.minimum(nb[hole], np.float32(cfg.no_reading_clear_m)) - margin, -np.inf)
    return reach, valid


def _reach_upper(depth_m: np.ndarray, config: EsdfConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An upper bound of :func:`free_reach` that needs no scans: exact on pixels with a reading,
    ``no_reading_clear_m - clear_margin_m`` on the others (their exact reach is that or less).

    Returns ``(upper (h, w) float32, valid (h, w) bool, clipped (h, w) float32)`` where
    ``clipped`` holds the readings clipped to ``max_range_m`` (inf without a reading); where
    the exact reach of a pixel without a reading is ``-inf`` for the whole frame (the rule off,
    or no reading at all) ``upper`` says so.
    """
    cfg = config
    with np.errstate(invalid="ignore"):
        valid = (depth_m >= np.float32(cfg.min_range_m)) & (depth_m < np.inf)
    clipped = np.where(valid, np.minimum(depth_m, np.float32(cfg.max_range_m)), np.float32(np.inf)).astype(np.float32)
    margin = np.float32(cfg.clear_margin_m)
    upper = clipped - margin
    if not valid.all():
        if cfg.no_reading_clear_m <= 0 or not valid.any():
            upper[~valid] = -np.inf
        else:
            upper[~valid] = np.float32(cfg.no_reading_clear_m) - margin
    return upper, valid, clipped


def _hole_reach(clipped: np.ndarray, valid: np.ndarray, rows: np.ndarray, cols: np.ndarray, config: EsdfConfig) -> np.ndarray:
    """:func:`free_reach` at the pixels ``(rows, cols)`` (k,) without a reading, computed for
    those pixels only: the first reading left and right of each is found by a binary search in
    the row-major list of reading pixels, up and down in the column-major one. (k,) float32.
    """
    h, w = valid.shape
    best = np.full(rows.shape, np.inf, dtype=np.float32)
    none_below = np.zeros(rows.shape, dtype=bool)
    for column, flat_valid, key, line_start, line_len, to_rc in (
        (False, np.flatnonzero(valid), rows * w + cols, rows * w, w, lambda f: (f // w, f % w)),
        (True, np.flatnonzero(valid.T), cols * h + rows, cols * h, h, lambda f: (f % h, f // h)),
    ):
        if flat_valid.size == 0:
            none_below[:] = True
            continue
        i = np.searchsorted(flat_valid, key)
        for after, j, ok in (
            (False, i - 1, i - 1 >= 0),
            (True, i, i < flat_valid.size),
        ):
            jj = np.clip(j, 0, flat_valid.size - 1)
            f = flat_valid[jj]
            ok = ok & (f >= line_start) & (f < line_start + line_len)
            if column and after:  # the column scan toward higher rows: down the image
                none_below = ~ok
            rr, cc = to_rc(f[ok])
            sel = np.flatnonzero(ok)
            best[sel] = np.minimum(best[sel], clipped[rr, cc])
    if config.no_reading_needs_below:
        best[none_below] = np.inf
    margin = np.float32(config.clear_margin_m)
    return np.where(np.isfinite(best), np.minimum(best, np.float32(config.no_reading_clear_m)) - margin, np.float32(-np.inf)).astype(np.float32)


class RollingOccupancy:
    """Log-odds occupancy in a window that moves with the vehicle by whole voxels.

    State: ``logodds`` float32 (nx, ny, nz); ``observed`` bool (ever hit or passed through);
    ``solid`` bool, the obstacle mask the distance transform sees: occupied voxels, plus unknown
    ones when ``unknown_policy == "occupied"``.
    """

    def __init__(self, config: EsdfConfig) -> None:
        self.config = config
        self.shape = config.grid_shape
        self._strides = np.array([self.shape[1] * self.shape[2], self.shape[2], 1], dtype=np.int64)
        self._unknown_solid = config.unknown_policy == "occupied"
        self._intrinsics: dict[tuple[PinholeCamera, int], o3d.core.Tensor] = {}
        self.origin_index = np.zeros(3, dtype=np.int64)
        self.logodds = np.zeros(self.shape, dtype=np.float32)
        self.observed = np.zeros(self.shape, dtype=bool)
        self.solid = np.full(self.shape, self._unknown_solid, dtype=bool)
        self._pristine = True  # no voxel observed since construction or reset
        self._scratch = np.zeros(int(np.prod(self.shape)), dtype=bool)
        # (camera, T_world_cam) of the latest frames before this one (body_clear_recent_views)
        self._recent_views: deque[tuple[PinholeCamera, np.ndarray]] = deque(maxlen=max(1, config.body_clear_recent_views))

    # -- geometry of the window -------------------------------------------------------------
    @property
    def voxel_m(self) -> float:
        return self.config.voxel_m

    def origin_for_center(self, center_world: np.ndarray) -> np.ndarray:
        """Global index of local voxel 0 that puts ``center_world`` (3,) in voxel ``shape // 2``."""
        g = np.floor(np.asarray(center_world, dtype=float) / self.voxel_m).astype(np.int64)
        return g - np.asarray(self.shape, dtype=np.int64) // 2

    def centers_of(self, flat: np.ndarray) -> np.ndarray:
        """World centres (k, 3), metres, of flat local indices ``flat`` (k,)."""
        idx = np.stack(np.unravel_index(flat, self.shape), axis=-1)
        return (idx + self.origin_index + 0.5) * self.voxel_m

    def reset(self) -> None:
        """Forget everything: every voxel unknown (the window stays where it is)."""
        self.logodds.fill(0.0)
        self.observed.fill(False)
        self.solid.fill(self._unknown_solid)
        self._pristine = True
        self._recent_views.clear()

    def shift_to(self, new_origin: np.ndarray) -> tuple[np.ndarray, list[IndexBox]]:
        """Move the window so local voxel 0 is global voxel ``new_origin`` (3,) int.

        Content that still overlaps keeps its global voxel (no resampling, so no smearing);
        voxels that enter are unknown. Returns ``(shift (3,) int, boxes)`` where ``boxes`` are
        the local index boxes whose obstacle state may differ from before for the distance
        transform: the entering slabs and the one-voxel slab at each face content left through
        (obstacles that left no longer count). A shift of a whole window or more resets the grid
        and returns the whole grid as one box.
        """
        new_origin = np.asarray(new_origin, dtype=np.int64)
        shift = new_origin - self.origin_index
        if not shift.any():
            return shift, []
        shape = np.asarray(self.shape)
        self.origin_index = new_origin.copy()
        if self._pristine:
            return shift, []  # nothing observed yet: an all-unknown window looks the same anywhere
        if np.any(np.abs(shift) >= shape):
            log.info("window jumped %s voxels (more than its size %s): map reset", shift.tolist(), list(self.shape))
            self.reset()
            return shift, [((0, 0, 0), tuple(int(n) for n in shape))]
        self.logodds = shift_array(self.logodds, shift, 0.0)
        self.observed = shift_array(self.observed, shift, False)
        self.solid = shift_array(self.solid, shift, self._unknown_solid)
        boxes: list[IndexBox] = []
        for axis in range(3):
            s = int(shift[axis])
            if s == 0:
                continue
            n = int(shape[axis])
            lo = [0, 0, 0]
            hi = [int(v) for v in shape]
            # Entering slab: content moved toward lower indices when s > 0.
            enter_lo, enter_hi = (n - s, n) if s > 0 else (0, -s)
            leave_lo, leave_hi = (0, 1) if s > 0 else (n - 1, n)
            for a, b in ((enter_lo, enter_hi), (leave_lo, leave_hi)):
                lo_b, hi_b = list(lo), list(hi)
                lo_b[axis], hi_b[axis] = a, b
                boxes.append((tuple(lo_b), tuple(hi_b)))
        return shift, boxes

    # -- one depth frame --------------------------------------------------------------------
    def integrate(
        self,
        depth_m: np.ndarray,
        camera: PinholeCamera,
        T_world_cam: np.ndarray,
        body_world: np.ndarray | None = None,
        body_margin_m: float = 0.0,
    ) -> OccupancyDelta:
        """Fuse one depth frame. Inputs are assumed validated (see ``EsdfMap.integrate``).

        Parameters
        ----------
        depth_m : float32 array, shape (camera.height, camera.width), z-depth in metres;
            0 / NaN / inf / negative / below ``min_range_m`` are no reading.
        camera : intrinsics of ``depth_m``
        T_world_cam : (4, 4) rigid transform, camera optical frame -> world
        body_world : (3,) metres, the vehicle's position; after the frame, the unknown voxels
            within ``body_clear_radius_m + body_margin_m`` of it are marked free. Default the
            camera position.
        body_margin_m : metres >= 0 added to the sphere's radius for this frame (the planner's
            tracking margin; see ``EsdfMap.integrate``).
        """
        cfg = self.config
        t0 = time.perf_counter()
        points = self._backproject(depth_m, camera, T_world_cam)
        t1 = time.perf_counter()

        flags = self._scratch
        hit_lin = self._hit_voxels(points, T_world_cam[:3, 3], flags)
        miss_lin = self._miss_voxels(depth_m, camera, T_world_cam, flags)
        flags[hit_lin] = False

        lo = self.logodds.reshape(-1)
        obs = self.observed.reshape(-1)
        solid = self.solid.reshape(-1)
        lo[hit_lin] = np.minimum(lo[hit_lin] + np.float32(cfg.hit_logodds), np.float32(cfg.max_logodds))
        lo[miss_lin] = np.maximum(lo[miss_lin] + np.float32(cfg.miss_logodds), np.float32(cfg.min_logodds))
        obs[hit_lin] = True
        obs[miss_lin] = True
        touched = np.concatenate([hit_lin, miss_lin])
        if touched.size:
            self._pristine = False
        now_solid = lo[touched] > np.float32(cfg.occupied_logodds)
        flipped = touched[now_solid != solid[touched]]
        solid[flipped] = ~solid[flipped]
        if cfg.body_clear_radius_m > 0:
            body = T_world_cam[:3, 3] if body_world is None else np.asarray(body_world, dtype=float)
            view = None if cfg.body_clear_in_view else (camera, T_world_cam)
            earlier = tuple(self._recent_views) if view is not None and cfg.body_clear_recent_views > 0 else ()
            cleared = self.mark_free_sphere(
                body, cfg.body_clear_radius_m + body_margin_m, view=view, earlier_views=earlier,
                above_m=None if cfg.body_clear_above_m is None else cfg.body_clear_above_m + body_margin_m,
            )
            if cleared.size:
                flipped = np.union1d(flipped, cleared)
        if cfg.body_clear_recent_views > 0:
            self._recent_views.append((camera, np.array(T_world_cam, dtype=float)))
        t2 = time.perf_counter()
        return OccupancyDelta(
            flipped=flipped,
            n_points=int(points.shape[0]),
            n_hit_voxels=int(hit_lin.size),
            n_miss_voxels=int(miss_lin.size),
            backproject_ms=(t1 - t0) * 1e3,
            update_ms=(t2 - t1) * 1e3,
        )

    def mark_free_sphere(
        self,
        center_world: np.ndarray,
        radius_m: float,
        view: tuple[PinholeCamera, np.ndarray] | None = None,
        earlier_views: tuple[tuple[PinholeCamera, np.ndarray], ...] = (),
        above_m: float | None = None,
    ) -> np.ndarray:
        """Mark the *unknown* voxels whose centre lies within ``radius_m`` of ``center_world``
        (3,) metres observed and free (one miss). Observed voxels are left alone.

        view : ``(camera, T_world_cam)`` of the frame just fused, or None. When given, voxels
            whose centre projects into that image (z-depth above ``min_range_m``) are left
            alone too: the camera has looked there, and a voxel it left unknown lies behind a
            surface or on a pixel without a reading (a dark or glass surface), which the
            vehicle's presence says nothing about.
        earlier_views : ``(camera, T_world_cam)`` of earlier frames: voxels whose centre
            projected into one of their images with a z-depth in (``min_range_m``,
            ``no_reading_clear_m``] are left alone as well (looked at from within the reach of
            the no-reading rule, and still unknown).
        above_m : metres, or None: voxels whose centre lies more than this above
            ``center_world`` are left alone (``EsdfConfig.body_clear_above_m``).

        Returns the flat local indices whose obstacle state flipped (unknown -> free under
        ``unknown_policy="occupied"``; none under ``"free"``).
        """
        cfg = self.config
        c = (np.asarray(center_world, dtype=float) / self.voxel_m) - self.origin_index - 0.5  # local, voxels
        r = float(radius_m) / self.voxel_m
        lo = np.maximum(np.ceil(c - r).astype(np.int64), 0)
        hi = np.minimum(np.floor(c + r).astype(np.int64) + 1, np.asarray(self.shape))
        if radius_m <= 0 or np.any(hi <= lo):
            return np.zeros(0, dtype=np.int64)
        ax = [np.arange(a, b) for a, b in zip(lo, hi)]
        d2 = (
            ((ax[0] - c[0]) ** 2)[:, None, None] + ((ax[1] - c[1]) ** 2)[None, :, None] + ((ax[2] - c[2]) ** 2)[None, None, :]
        )
        box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
        inside = d2 <= r * r
        if above_m is not None:
            inside &= (ax[2] - c[2])[None, None, :] <= float(above_m) / self.voxel_m
        new = inside & ~self.observed[box]
        if view is not None and new.any():
            new[self._projects_into(view, lo, new)] = False
        for past in earlier_views:
            if not new.any():
                break
            new[self._projects_into(past, lo, new, max_z_m=cfg.no_reading_clear_m)] = False
        if not new.any():
            return np.zeros(0, dtype=np.int64)
        self._pristine = False
        self.observed[box] |= new
        lo_box = self.logodds[box]
        lo_box[new] = np.float32(max(cfg.miss_logodds, cfg.min_logodds))
        sub = np.flatnonzero(new & self.solid[box])
        self.solid[box] &= ~new
        if sub.size == 0:
            return np.zeros(0, dtype=np.int64)
        idx = np.stack(np.unravel_index(sub, new.shape), axis=-1) + lo
        return (idx[:, 0] * self.shape[1] + idx[:, 1]) * self.shape[2] + idx[:, 2]

    def _projects_into(
        self, view: tuple[PinholeCamera, np.ndarray], lo: np.ndarray, mask: np.ndarray, max_z_m: float = np.inf
    ) -> tuple[np.ndarray, ...]:
        """Indices into ``mask`` (a box of the grid starting at local voxel ``lo``) of its True
        voxels whose centre projects into the image of ``view = (camera, T_world_cam)``, at
        least half a pixel inside its border, with a z-depth above ``min_range_m`` (the pixel
        rule of the clearing step) and at most ``max_z_m``."""
        camera, T_world_cam = view
        sub = np.nonzero(mask)
        centres = (np.stack(sub, axis=-1) + lo + self.origin_index + 0.5) * self.voxel_m
        p_cam = (centres - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
        z = p_cam[:, 2]
        seen = (z > self.config.min_range_m) & (z <= max_z_m)
        zs = np.where(seen, z, 1.0)
        # pixel coordinates (pixel i spans [i - 0.5, i + 0.5)), half a pixel inside the border:
        # a voxel centre on the frustum's edge (a 45 deg diagonal from a voxel-aligned start)
        # is in the image for float64 here and out of it for the clearing's float32, and the
        # two together left it unknown, an obstacle 0.21 m from the vehicle
        u = camera.fx * p_cam[:, 0] / zs + camera.cx
        v = camera.fy * p_cam[:, 1] / zs + camera.cy
        seen &= (u >= 0.0) & (u <= camera.width - 1.0) & (v >= 0.0) & (v <= camera.height - 1.0)
        return tuple(a[seen] for a in sub)

    def _backproject(self, depth_m: np.ndarray, camera: PinholeCamera, T_world_cam: np.ndarray) -> np.ndarray:
        """World points (n, 3) float32 of the strided readings in [min_range_m, max_range_m).

        Open3D's ``create_from_depth_image`` drops 0, NaN, inf, negative and readings at or
        beyond ``depth_max``; the dead zone below ``min_range_m`` is zeroed here first.
        """
        cfg = self.config
        s = cfg.stride_px
        d = depth_m[::s, ::s]
        with np.errstate(invalid="ignore"):
            d = np.where(d >= cfg.min_range_m, d, np.float32(0.0)) if cfg.min_range_m > 0 else np.ascontiguousarray(d)
        key = (camera, s)
        K = self._intrinsics.get(key)
        if K is None:
            Kn = np.array(
                [[camera.fx / s, 0.0, camera.cx / s], [0.0, camera.fy / s, camera.cy / s], [0.0, 0.0, 1.0]]
            )
            K = self._intrinsics[key] = o3d.core.Tensor(Kn)
        pcd = o3d.t.geometry.PointCloud.create_from_depth_image(
            o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(d)),
            K,
            o3d.core.Tensor(invert_transform(T_world_cam)),
            depth_scale=1.0,
            depth_max=float(cfg.max_range_m),
            stride=1,
        )
        return pcd.point.positions.numpy()

    def _flat_in_grid(self, points: np.ndarray) -> np.ndarray:
        """Flat local indices (k,) of the voxels holding ``points`` (n, 3) world metres.

        Points outside the window are dropped. Column-wise int32 arithmetic: the unsigned view
        folds the ``>= 0`` test into the ``< n`` test.
        """
        inv_v = np.float32(1.0 / self.voxel_m)
        nx, ny, nz = self.shape
        ix = np.floor(points[:, 0] * inv_v).astype(np.int32) - np.int32(self.origin_index[0])
        iy = np.floor(points[:, 1] * inv_v).astype(np.int32) - np.int32(self.origin_index[1])
        iz = np.floor(points[:, 2] * inv_v).astype(np.int32) - np.int32(self.origin_index[2])
        inside = (
            (ix.view(np.uint32) < nx) & (iy.view(np.uint32) < ny) & (iz.view(np.uint32) < nz)
        )
        return (ix[inside].astype(np.int64) * ny + iy[inside]) * nz + iz[inside]

    def _hit_voxels(self, points: np.ndarray, cam_pos: np.ndarray, flags: np.ndarray) -> np.ndarray:
        """Distinct flat indices hit by ``points`` (n, 3) world, plus the surface-thickness band.

        Leaves ``flags`` set at the returned indices (the caller clears them).
        """
        cfg = self.config
        flags[self._flat_in_grid(points)] = True
        surface = np.flatnonzero(flags)
        n_band = int(round(cfg.surface_thickness_m / cfg.voxel_m))
        if n_band > 0 and surface.size:
            c = self.centers_of(surface)
            ray = c - cam_pos
            ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-9)
            steps = np.arange(1, n_band + 1, dtype=float) * cfg.voxel_m
            behind = (c[:, None, :] + ray[:, None, :] * steps[None, :, None]).reshape(-1, 3)
            flags[self._flat_in_grid(behind.astype(np.float32))] = True
            return np.flatnonzero(flags)
        return surface

    def _frustum_box(self, camera: PinholeCamera, T_world_cam: np.ndarray) -> IndexBox | None:
        """Local index box around the camera frustum cut at ``max_range_m``, or None if outside."""
        r = self.config.max_range_m
        w, h = camera.width - 1.0, camera.height - 1.0
        corners_px = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
        P_cam = np.vstack([np.zeros((1, 3)), camera.back_project(corners_px, np.full(4, r))])
        P = P_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        g_lo = np.floor(P.min(axis=0) / self.voxel_m).astype(np.int64) - self.origin_index
        g_hi = np.floor(P.max(axis=0) / self.voxel_m).astype(np.int64) - self.origin_index + 1
        lo = np.maximum(g_lo, 0)
        hi = np.minimum(g_hi, np.asarray(self.shape))
        if np.any(hi <= lo):
            return None
        return tuple(int(v) for v in lo), tuple(int(v) for v in hi)

    def _frustum_blocks(
        self, camera: PinholeCamera, T_world_cam: np.ndarray, box: IndexBox, reach_img: np.ndarray | None = None
    ) -> np.ndarray:
        """Bool mask over ``box``: False on blocks of ``_BLOCK``^3 voxels lying wholly outside the
        view frustum (beyond one of its four side planes, nearer than ``min_range_m`` or beyond
        ``max_range_m``, each by more than the block's half-diagonal). A cull only: every voxel
        it drops projects outside the image or out of range.

        With ``reach_img`` (h, w) (:func:`free_reach`) also False on blocks wholly in front of the
        camera whose nearest voxel centre is at or beyond the largest reach over the pixel
        rectangle the block's centres project into (see :meth:`_beyond_reach`): none of their
        voxels can be passed through."""
        cfg = self.config
        lo, hi = np.asarray(box[0]), np.asarray(box[1])
        nb = (hi - lo + _BLOCK - 1) // _BLOCK
        v = cfg.voxel_m
        # block centres, world -> camera frame
        axes = [(lo[k] + self.origin_index[k] + (np.arange(nb[k]) + 0.5) * _BLOCK) * v for k in range(3)]
        C = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        P = (C - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        r = 0.5 * np.sqrt(3.0) * _BLOCK * v + 1e-6
        keep = (z > cfg.min_range_m - r) & (z < cfg.max_range_m + r)
        # side planes through the optical centre at the image's outer pixel edges
        xl, xr = (-0.5 - camera.cx) / camera.fx, (camera.width - 0.5 - camera.cx) / camera.fx
        yt, yb = (-0.5 - camera.cy) / camera.fy, (camera.height - 0.5 - camera.cy) / camera.fy
        keep &= (x - xr * z) / np.hypot(1.0, xr) < r
        keep &= (xl * z - x) / np.hypot(1.0, xl) < r
        keep &= (y - yb * z) / np.hypot(1.0, yb) < r
        keep &= (yt * z - y) / np.hypot(1.0, yt) < r
        if reach_img is not None and keep.any():
            k = np.flatnonzero(keep)
            keep[k] = ~self._beyond_reach(camera, T_world_cam, C[k], reach_img)
        mask = keep.reshape(tuple(nb))
        for axis in range(3):
            mask = np.repeat(mask, _BLOCK, axis=axis)
        return mask[: hi[0] - lo[0], : hi[1] - lo[1], : hi[2] - lo[2]]

    def _beyond_reach(
        self, camera: PinholeCamera, T_world_cam: np.ndarray, centers: np.ndarray, reach_img: np.ndarray
    ) -> np.ndarray:
        """Bool (k,): True where no voxel centre of the ``_BLOCK``^3 block centred at
        ``centers`` (k, 3) world can be passed through this frame.

        The block's voxel centres fill the box ``center +- (_BLOCK - 1) / 2 voxels``. When all
        of its corners lie beyond ``min_range_m`` in front of the camera, the centres project
        (convexity of the perspective image of a box in front of the camera) into the pixel
        rectangle spanned by the corners' pixels, rounded as :meth:`_miss_voxels` rounds, and
        every centre's z-depth is at least the corners' least. If that least depth is at or
        beyond the largest reach over the rectangle (a superset: its 8 x 8-pixel tiles), no
        centre satisfies ``z < reach[pixel]``. A block partly near or behind the camera is
        never culled; one whose rectangle misses the image is culled (no centre projects in).
        """
        cfg = self.config
        half = 0.5 * (_BLOCK - 1) * cfg.voxel_m
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        corners = centers[:, None, :] + half * signs[None, :, :]  # (k, 8, 3)
        P = (corners - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
        z = P[..., 2]
        zmin = z.min(axis=1)
        ahead = zmin > cfg.min_range_m
        out = np.zeros(len(centers), dtype=bool)
        if not ahead.any():
            return out
        P, z, zmin = P[ahead], z[ahead], zmin[ahead]
        u = camera.fx * P[..., 0] / z + camera.cx + 0.5
        v = camera.fy * P[..., 1] / z + camera.cy + 0.5
        # one pixel of slack on each side and 1 mm in depth: the clearing projects in float32
        u0 = np.maximum(np.floor(u.min(axis=1)) - 1, 0).astype(np.int64)
        u1 = np.minimum(np.floor(u.max(axis=1)) + 1, camera.width - 1).astype(np.int64)
        v0 = np.maximum(np.floor(v.min(axis=1)) - 1, 0).astype(np.int64)
        v1 = np.minimum(np.floor(v.max(axis=1)) + 1, camera.height - 1).astype(np.int64)
        outside = (u1 < u0) | (v1 < v0)
        table = _TileMax(reach_img)
        top = np.full(len(zmin), np.inf)
        inside = ~outside
        top[inside] = table.query(v0[inside], v1[inside], u0[inside], u1[inside])
        out[ahead] = outside | (zmin >= top + 1e-3)
        return out

    def _miss_voxels(
        self, depth_m: np.ndarray, camera: PinholeCamera, T_world_cam: np.ndarray, flags: np.ndarray
    ) -> np.ndarray:
        """Flat indices of solid voxels in the frustum that this frame sees through
        (their centre's z-depth below the pixel's :func:`free_reach`).

        Only ``solid`` voxels can change the field by being passed through: obstacles, plus
        unknown voxels under ``unknown_policy == "occupied"``. Voxels hit in this frame
        (``flags``) are skipped.
        """
        cfg = self.config
        box = self._frustum_box(camera, T_world_cam)
        if box is None:
            return np.zeros(0, dtype=np.int64)
        (x0, y0, z0), (x1, y1, z1) = box
        window = (slice(x0, x1), slice(y0, y1), slice(z0, z1))
        cand = self.solid[window] & ~flags.reshape(self.shape)[window]
        if cfg.reach_cull:
            # scans only where a voxel needs them: a cheap upper bound culls blocks and voxels,
            # the exact reach of a pixel without a reading is computed for the survivors only
            reach_img, valid_img, clipped = _reach_upper(depth_m, cfg)
            lazy = not valid_img.all() and cfg.no_reading_clear_m > 0 and valid_img.any()
        else:
            reach_img, valid_img = free_reach(depth_m, cfg)
            lazy = False
        if cand.size >= 8 * _BLOCK**3:
            cand &= self._frustum_blocks(camera, T_world_cam, box, reach_img if cfg.reach_cull else None)
        ix, iy, iz = np.nonzero(cand)  # C-level unravel: no integer division in numpy
        if ix.size == 0:
            return np.zeros(0, dtype=np.int64)
        # Voxel centres in the camera frame: R^T (c - t), c = (i + origin + 0.5) * voxel, from
        # per-axis tables (the same float32 arithmetic as per voxel).
        R = T_world_cam[:3, :3]
        t = T_world_cam[:3, 3]
        v = cfg.voxel_m
        a = (self.origin_index + 0.5) * v - t  # (3,)
        cx_w = (np.arange(x0, x1) * v + a[0]).astype(np.float32)[ix]
        cy_w = (np.arange(y0, y1) * v + a[1]).astype(np.float32)[iy]
        cz_w = (np.arange(z0, z1) * v + a[2]).astype(np.float32)[iz]
        flat = ((ix + x0) * self.shape[1] + (iy + y0)) * self.shape[2] + (iz + z0)
        Rt = R.T.astype(np.float32)
        xc = Rt[0, 0] * cx_w + Rt[0, 1] * cy_w + Rt[0, 2] * cz_w
        yc = Rt[1, 0] * cx_w + Rt[1, 1] * cy_w + Rt[1, 2] * cz_w
        zc = Rt[2, 0] * cx_w + Rt[2, 1] * cy_w + Rt[2, 2] * cz_w
        front = zc > np.float32(cfg.min_range_m)
        flat, xc, yc, zc = flat[front], xc[front], yc[front], zc[front]
        u = np.floor(np.float32(camera.fx) * xc / zc + np.float32(camera.cx + 0.5)).astype(np.int64)
        vv = np.floor(np.float32(camera.fy) * yc / zc + np.float32(camera.cy + 0.5)).astype(np.int64)
        inside = (u >= 0) & (u < camera.width) & (vv >= 0) & (vv < camera.height)
        flat, zc = flat[inside], zc[inside]
        vv, u = vv[inside], u[inside]
        miss = zc < reach_img[vv, u]
        if lazy:
            # the upper bound let these through; pixels without a reading get their exact reach
            m = np.flatnonzero(miss & ~valid_img[vv, u])
            if m.size:
                pix = vv[m] * camera.width + u[m]
                uniq, inv = np.unique(pix, return_inverse=True)
                exact = _hole_reach(clipped, valid_img, uniq // camera.width, uniq % camera.width, cfg)
                miss[m] = zc[m] < exact[inv]
        if not valid_img.all():
            # a pixel without a reading never clears an observed obstacle
            occupied = self.observed.reshape(-1)[flat] & (self.logodds.reshape(-1)[flat] > np.float32(cfg.occupied_logodds))
            miss &= valid_img[vv, u] | ~occupied
        return flat[miss]


#: Tile edge, in pixels, of the range-maximum table over the reach image.
_TILE = 8


class _TileMax:
    """Maximum of an image over pixel rectangles, rounded out to ``_TILE`` x ``_TILE`` tiles: a
    2-D sparse table of tile maxima (``levels[a][b][i, j]`` = max over tiles ``[i, i + 2^a) x
    [j, j + 2^b)``), so one query costs four lookups whatever the rectangle's size."""

    def __init__(self, image: np.ndarray) -> None:
        h, w = image.shape
        th, tw = -(-h // _TILE), -(-w // _TILE)
        if h % _TILE or w % _TILE:
            padded = np.full((th * _TILE, tw * _TILE), -np.inf, dtype=np.float32)
            padded[:h, :w] = image
        else:
            padded = np.asarray(image, dtype=np.float32)
        tiles = padded.reshape(th, _TILE, tw, _TILE).max(axis=3).max(axis=1)
        rows = [tiles]
        while (1 << len(rows)) <= th:
            prev, s = rows[-1], 1 << (len(rows) - 1)
            rows.append(np.maximum(prev[:-s], prev[s:]))
        self.levels = []
        for r in rows:
            cols = [r]
            while (1 << len(cols)) <= tw:
                prev, s = cols[-1], 1 << (len(cols) - 1)
                cols.append(np.maximum(prev[:, :-s], prev[:, s:]))
            self.levels.append(cols)

    def query(self, r0: np.ndarray, r1: np.ndarray, c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """Max over pixel rows ``r0..r1`` and columns ``c0..c1`` (inclusive, int arrays (k,))
        of the tiles they touch, (k,)."""
        t0, t1 = r0 // _TILE, r1 // _TILE
        s0, s1 = c0 // _TILE, c1 // _TILE
        a = np.floor(np.log2(t1 - t0 + 1)).astype(np.int64)
        b = np.floor(np.log2(s1 - s0 + 1)).astype(np.int64)
        out = np.empty(len(r0))
        for ai in np.unique(a):
            for bi in np.unique(b[a == ai]):
                m = (a == ai) & (b == bi)
                L = self.levels[ai][bi]
                i0, i1 = t0[m], t1[m] - (1 << ai) + 1
                j0, j1 = s0[m], s1[m] - (1 << bi) + 1
                out[m] = np.maximum(np.maximum(L[i0, j0], L[i0, j1]), np.maximum(L[i1, j0], L[i1, j1]))
        return out


def shift_array(a: np.ndarray, shift: np.ndarray, fill) -> np.ndarray:
    """Array ``b`` with ``b[i] = a[i + shift]`` where that index exists, ``fill`` elsewhere.

    Parameters
    ----------
    a : array, shape (nx, ny, nz)
    shift : int array (3,), voxels the window moved (new origin minus old origin)
    """
    out = np.full(a.shape, fill, dtype=a.dtype)
    if any(abs(int(s)) >= n for s, n in zip(shift, a.shape)):
        return out  # moved by a whole window or more: nothing overlaps
    src, dst = [], []
    for s, n in zip(shift, a.shape):
        s = int(s)
        if s >= 0:
            src.append(slice(s, n))
            dst.append(slice(0, n - s))
        else:
            src.append(slice(0, n + s))
            dst.append(slice(-s, n))
    out[tuple(dst)] = a[tuple(src)]
    return out
