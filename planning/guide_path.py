"""Front-end of the local planner: a clearance-aware grid search that guides the MPC.

A receding-horizon MPC with linearized clearance sees obstacles as half-spaces at its knots:
behind a wall it stops at the wall even when the wall ends a metre away (a local minimum).
Fast-Planner, which the paper adopts, pairs its optimizer with a search front-end; this is
ours, kept small:

- :func:`segment_clear` says whether the straight segment to the goal keeps the clearance.
  When it does, the MPC is pulled straight to the goal and no search runs.
- Otherwise :func:`search_guide_path` runs Dijkstra on a 26-connected voxel grid spanning the
  vehicle and the goal (plus a margin), over cells whose field distance is at least the
  required clearance; edge costs are lengths inflated where clearance is below a preferred
  value, so the path keeps away from walls. The grid, its field query and the graph are
  vectorized (NumPy + ``scipy.sparse.csgraph``).
- :func:`carrot_on_path` picks the point a fixed arc length ahead of the vehicle's nearest
  path point: the MPC's attractor for this step.

Everything is in world ENU metres.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from planning.field import DistanceField

__all__ = ["segment_points", "segment_clear", "search_guide_path", "carrot_on_path"]

logger = logging.getLogger(__name__)

# half of the 26 neighbour offsets (the other half are their negatives)
_OFFSETS = np.array(
    [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)]
)


def segment_points(a: np.ndarray, b: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points from ``a`` (3,) to ``b`` (3,) inclusive, at most ``spacing_m`` apart, (n, 3)."""
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / spacing_m)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    return a[None, :] + t * (b - a)[None, :]


def segment_clear(dist: np.ndarray, clearance_m: float) -> bool:
    """True when every sampled distance (n,) along a segment is at least ``clearance_m``."""
    return bool(np.all(dist >= clearance_m))


def search_guide_path(
    field: DistanceField,
    start: np.ndarray,
    goal: np.ndarray,
    clearance_m: float,
    preferred_clearance_m: float,
    resolution_m: float = 0.25,
    margin_xy_m: float = 3.0,
    margin_z_m: float = 1.5,
    max_cells: int = 60000,
    z_min_m: float | None = None,
) -> np.ndarray | None:
    """Shortest clearance-aware path from ``start`` to ``goal`` on a voxel grid.

    Parameters
    ----------
    field : DistanceField
    start, goal : arrays (3,), metres, world ENU
    clearance_m : cells with distance below this are blocked (the start and goal cells are
        always allowed, so a start inside the margin can leave it)
    preferred_clearance_m : edges through cells with less clearance cost up to 3x their
        length, linearly in the shortfall
    resolution_m : grid spacing; increased automatically to keep at most ``max_cells``
    margin_xy_m, margin_z_m : grid extent around the bounding box of start and goal
    z_min_m : optional floor of the grid (e.g. the ground)

    Returns
    -------
    array (n, 3) of cell centres from start to goal (first = start, last = goal), or None
    when the goal cannot be reached inside the grid.
    """
    lo = np.minimum(start, goal) - np.array([margin_xy_m, margin_xy_m, margin_z_m])
    hi = np.maximum(start, goal) + np.array([margin_xy_m, margin_xy_m, margin_z_m])
    if z_min_m is not None:
        lo[2] = max(lo[2], z_min_m)
        hi[2] = max(hi[2], lo[2] + resolution_m)
    extent = hi - lo
    res = resolution_m
    cells = np.prod(np.ceil(extent / res) + 1)
    if cells > max_cells:
        res = resolution_m * (cells / max_cells) ** (1.0 / 3.0)
    shape = (np.ceil(extent / res).astype(int) + 1)
    nx, ny, nz = (int(s) for s in shape)
    gx = lo[0] + res * np.arange(nx)
    gy = lo[1] + res * np.arange(ny)
    gz = lo[2] + res * np.arange(nz)
    X, Y, Z = np.meshgrid(gx, gy, gz, indexing="ij")
    centres = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    dist, _ = field.query(centres)
    dist = np.asarray(dist, dtype=float)

    def cell_of(p: np.ndarray) -> int:
        ijk = np.clip(np.round((p - lo) / res).astype(int), 0, shape - 1)
        return int(np.ravel_multi_index(tuple(ijk), (nx, ny, nz)))

    s_idx, g_idx = cell_of(start), cell_of(goal)
    free = dist >= clearance_m
    free[s_idx] = free[g_idx] = True
    free3 = free.reshape(nx, ny, nz)
    penalty = 1.0 + 2.0 * np.clip((preferred_clearance_m - dist) / max(preferred_clearance_m - clearance_m, 1e-6), 0.0, 1.0)
    pen3 = penalty.reshape(nx, ny, nz)
    idx3 = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    rows, cols, wts = [], [], []
    for dx, dy, dz in _OFFSETS:
        sa = (slice(max(0, -dx), nx - max(0, dx)), slice(max(0, -dy), ny - max(0, dy)), slice(max(0, -dz), nz - max(0, dz)))
        sb = (
            slice(max(0, dx), nx + min(0, dx)),
            slice(max(0, dy), ny + min(0, dy)),
            slice(max(0, dz), nz + min(0, dz)),
        )
        ok = free3[sa] & free3[sb]
        if not ok.any():
            continue
        length = res * float(np.sqrt(dx * dx + dy * dy + dz * dz))
        rows.append(idx3[sa][ok])
        cols.append(idx3[sb][ok])
        wts.append(length * 0.5 * (pen3[sa][ok] + pen3[sb][ok]))
    if not rows:
        return None
    n = nx * ny * nz
    graph = sp.csr_matrix((np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    dist_to, pred = dijkstra(graph, directed=False, indices=s_idx, return_predecessors=True)
    if not np.isfinite(dist_to[g_idx]):
        logger.debug("guide path: goal unreachable in a %dx%dx%d grid", nx, ny, nz)
        return None
    chain = [g_idx]
    while chain[-1] != s_idx:
        chain.append(int(pred[chain[-1]]))
    path = centres[np.array(chain[::-1])]
    path[0], path[-1] = start, goal
    return path


def carrot_on_path(path: np.ndarray, position: np.ndarray, lookahead_m: float) -> tuple[np.ndarray, int]:
    """The point ``lookahead_m`` of arc length ahead of the path point nearest ``position``.

    Parameters
    ----------
    path : array (n, 3), metres; position : array (3,)

    Returns
    -------
    carrot (3,), index of the nearest path point
    """
    i = int(np.argmin(np.sum((path - position) ** 2, axis=1)))
    seg = np.linalg.norm(np.diff(path[i:], axis=0), axis=1)
    if seg.size == 0:
        return path[-1].copy(), i
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= lookahead_m:
        return path[-1].copy(), i
    j = int(np.searchsorted(s, lookahead_m))
    t = (lookahead_m - s[j - 1]) / max(s[j] - s[j - 1], 1e-12)
    return path[i + j - 1] + t * (path[i + j] - path[i + j - 1]), i
