"""The floor apart from the rest of the map: a plane below, and a distance field without it.

Why. The planner keeps ``d_safe_m`` plus its measured tracking error from every obstacle
(:class:`planning.planner.InflatedField`). A multicopter in gusts wanders far more sideways
than up and down (PX4's vertical velocity gain is twice the horizontal one, and gusts near
the ground are mostly horizontal: ``docs/robustness.md``), yet one number inflates the floor
too, so under a 0.95 m horizontal error the vehicle must keep 1.4 m over the ground and no
goal beside a target lower than that has the clearance. A floor is a plane: a vehicle can only
reach it by its *vertical* error. Inflating the floor by the vertical error and everything else
by the full one needs to know which distance is the floor's, and a distance field keeps only
the nearest obstacle's. So the floor is taken out of it:

- :func:`floor_top_index` finds the floor's top voxel layer from the occupied voxels below the
  vehicle (the lowest occupied voxel of each column; the layer most columns end on, and the
  layers just above it that depth noise spreads the floor into);
- :class:`FloorSplit` holds the plane (every obstacle voxel, seen or unknown, whose centre is at
  or under ``top_m``) and the exact distance field of all the *other* obstacle voxels.

Soundness does not rest on the estimate. Every voxel the split calls floor lies at or under
``top_m``, so its distance from a point ``p`` is at least ``p_z - top_m``; every other voxel is in
the field. A wrong estimate only makes the split less useful (a floor layer left in the field
keeps the full margin), never less safe. Terrain that rises above the estimate, a platform, a
low object: all of it is "the rest".

Frames and units: world ENU, metres; voxel centres as :class:`planning.esdf.EsdfMap`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planning.esdf_interp import interpolate_grid

__all__ = ["FloorSplit", "floor_top_index", "FLOOR_MIN_COLUMNS", "FLOOR_TAIL_FRACTION"]

#: Fewest columns (0.1 m voxels: 0.5 m^2) whose lowest occupied voxel is on the modal layer
#: before that layer is taken as a floor.
FLOOR_MIN_COLUMNS = 50
#: A layer just above the floor's modal layer belongs to the floor while at least this fraction
#: of the modal layer's columns end on it. Measured on the held-out yard under the ``realistic``
#: profile (D435 noise, odometry drift): the layer above the mode holds 5-11 % of the columns,
#: the next one 0.6-0.8 % (low objects standing on the ground).
FLOOR_TAIL_FRACTION = 0.02


def floor_top_index(
    occupied: np.ndarray,
    below_k: int,
    min_columns: int = FLOOR_MIN_COLUMNS,
    tail_fraction: float = FLOOR_TAIL_FRACTION,
) -> int | None:
    """The local z index of the floor's top voxel layer, or None when no floor is seen.

    Parameters
    ----------
    occupied : bool (nx, ny, nz), observed obstacle voxels of the map window
    below_k : only voxels with z index < ``below_k`` count (the vehicle's layer: a ceiling or
        the underside of a beam over the vehicle is never the floor)
    min_columns : fewest columns ending on the modal layer for it to be a floor
    tail_fraction : a layer above the modal one joins the floor while at least this fraction of
        the modal layer's column count ends on it (depth noise spreads a floor over a layer or
        two); the first layer under the fraction ends the floor

    Returns
    -------
    int or None : z index (local, ``0 <= k < below_k``); None when ``below_k <= 0`` or fewer
        than ``min_columns`` columns end on the modal layer
    """
    occ = np.asarray(occupied, dtype=bool)
    if occ.ndim != 3:
        raise ValueError(f"occupied must be a 3-D bool array, got shape {occ.shape}")
    below_k = min(int(below_k), occ.shape[2])
    if below_k <= 0:
        return None
    low = occ[:, :, :below_k]
    has = low.any(axis=2)
    if not has.any():
        return None
    lowest = np.argmax(low, axis=2)[has]
    counts = np.bincount(lowest, minlength=below_k)
    mode = int(np.argmax(counts))
    if counts[mode] < min_columns:
        return None
    top = mode
    while top + 1 < below_k and counts[top + 1] >= tail_fraction * counts[mode]:
        top += 1
    return top


@dataclass(frozen=True)
class FloorSplit:
    """The floor as a plane and the distance field of every other obstacle voxel.

    Attributes
    ----------
    top_m : float, world z of the highest floor voxel centre, metres; every voxel the split
        counts as floor has its centre at or under it
    rest : float32 (nx, ny, nz), read-only, distance at voxel centres to the nearest obstacle
        voxel that is not floor, metres, clamped at the map's ``max_distance_m`` (0 at such
        voxels, no inside distance; 0 under the floor's top layer, where no point is outside
        an obstacle)
    origin_index : int (3,), global lattice index of ``rest[0, 0, 0]``
    voxel_m : float, voxel edge, metres
    """

    top_m: float
    rest: np.ndarray
    origin_index: np.ndarray
    voxel_m: float

    def plane_distance(self, points: np.ndarray) -> np.ndarray:
        """A lower bound of the distance from each point (n, 3) to every floor voxel centre:
        ``p_z - top_m`` (negative at or under the floor), metres, shape (n,)."""
        return np.asarray(points, dtype=float)[:, 2] - self.top_m

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance (n,) and gradient (n, 3) of the rest of the map at ``points`` (n, 3) world
        metres, trilinear between voxel centres as :meth:`planning.esdf.EsdfMap.query`, and a
        bool (n,) that is False where a point lies outside the window (its values there are
        not to be used)."""
        P = np.asarray(points, dtype=float)
        dist, grad, excess = interpolate_grid(self.rest, self.origin_index, self.voxel_m, P)
        return dist, grad, ~np.any(excess != 0.0, axis=1)
