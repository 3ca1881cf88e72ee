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
- Budgets (a real-time step must have a bounded worst case): the grid never has more than
  ``max_cells`` cells (it is coarsened to fit), and with a time budget the search runs coarse
  to fine and stops refining before a level it predicts will overrun (:func:`guide_search`).
- Limits: the grid can be clipped to a box (the operator's flight volume shrunk by the body
  radius) and to a floor and a ceiling, so the path never leaves them; cells the field
  reports as unknown space (``field.is_unknown(points)``, or ``not field.known(points)`` as
  :class:`planning.esdf.EsdfMap` answers) are blocked. With the ESDF's default unknown policy
  ("occupied") its distance already makes unknown space an obstacle; the mask matters with
  the "free" policy, where the MPC may cross unknown space but the guide will not route it.
- :func:`carrot_on_path` picks the point a fixed arc length ahead of the vehicle's nearest
  path point: the MPC's attractor for this step.

Everything is in world ENU metres.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from planning.field import DistanceField

__all__ = [
    "segment_points", "segment_clear", "search_guide_path", "guide_search", "GuideResult", "carrot_on_path",
    "unknown_mask",
]

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


@dataclass(frozen=True, eq=False)
class GuideResult:
    """One guide search (:func:`guide_search`).

    Attributes
    ----------
    path : array (n, 3) of cell centres from start to goal (first = start, last = goal), world
        ENU metres, or None when no level found the goal reachable
    status : ``"found"`` (the finest level planned ran), ``"budget"`` (the time budget stopped
        the refinement; ``path`` is the finest completed level's, possibly None),
        ``"unreachable"`` (every level ran and none reached the goal)
    resolution_m : grid spacing of the level ``path`` comes from (of the last level run when
        there is no path), metres
    cells : grid cells of that level
    elapsed_ms : wall time of the whole search, milliseconds
    levels_run : number of levels completed
    """

    path: np.ndarray | None
    status: str
    resolution_m: float
    cells: int
    elapsed_ms: float
    levels_run: int


def _grid_level(
    field: DistanceField,
    start: np.ndarray,
    goal: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    res: float,
    clearance_m: float,
    preferred_clearance_m: float,
    unknown_blocked: bool,
) -> np.ndarray | None:
    """Dijkstra on one grid spanning ``[lo, hi]`` (every cell centre inside it) at ``res``."""
    extent = hi - lo
    shape = np.floor(extent / res + 1e-9).astype(int) + 1
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
    if unknown_blocked:
        unknown = unknown_mask(field, centres)
        if unknown is not None:
            free &= ~unknown
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


def unknown_mask(field: DistanceField, points: np.ndarray) -> np.ndarray | None:
    """Which ``points`` (n, 3) the field reports as unknown space, bool (n,), or None when it
    cannot say. Uses ``field.is_unknown(points)`` if present, else ``~field.known(points)``
    (:meth:`planning.esdf.EsdfMap.known`: the voxel was hit, passed through by a ray or inside
    the vehicle's body sphere). Public methods only; an analytic field has neither."""
    for name, negate in (("is_unknown", False), ("known", True)):
        fn = getattr(field, name, None)
        if callable(fn):
            mask = np.asarray(fn(points), dtype=bool).reshape(-1)
            if mask.shape != (points.shape[0],):
                raise ValueError(f"field.{name} returned shape {mask.shape}, expected ({points.shape[0]},)")
            return ~mask if negate else mask
    return None


def _cells(extent: np.ndarray, res: float) -> float:
    return float(np.prod(np.floor(extent / res + 1e-9) + 1))


def _lattice_through(start: np.ndarray, lo: np.ndarray, hi: np.ndarray, res: float) -> np.ndarray:
    """The grid's lowest corner: ``lo`` raised by less than ``res`` on each axis whose range
    ``[lo, hi]`` holds ``start``, so that ``start`` is a cell centre.

    A cell is free only when its centre keeps the clearance, and a passage whose free band is
    thinner than the spacing (a duct above a desk, each 0.6 m from the height the vehicle flies
    at, leaves a band of about 0.2 m at a 0.55 m clearance) is seen by the grid only when a layer
    of centres falls in it. The vehicle is there already: a lattice through its position always
    has the layer it flies at (and a search leg's end is mostly at that height too), wherever
    the flight volume's floor puts ``lo``.
    """
    s, lo = np.asarray(start, dtype=float), np.asarray(lo, dtype=float)
    inside = (s >= lo) & (s <= hi)
    aligned = s - np.floor((s - lo) / res + 1e-9) * res
    return np.where(inside, aligned, lo)


def guide_search(
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
    z_max_m: float | None = None,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    time_budget_s: float | None = None,
    unknown_blocked: bool = True,
) -> GuideResult:
    """Shortest clearance-aware path from ``start`` to ``goal`` on a voxel grid, with budgets.

    Parameters
    ----------
    field : DistanceField; if it also has ``is_unknown(points (n, 3)) -> bool (n,)`` or
        ``known(points) -> bool (n,)`` (the ESDF's), cells it reports unknown are blocked
        (``unknown_blocked``; see :func:`unknown_mask`)
    start, goal : arrays (3,), metres, world ENU
    clearance_m : cells with distance below this are blocked (the start and goal cells are
        always allowed, so a start inside the margin can leave it)
    preferred_clearance_m : edges through cells with less clearance cost up to 3x their
        length, linearly in the shortfall
    resolution_m : finest grid spacing; increased automatically to keep at most ``max_cells``
    margin_xy_m, margin_z_m : grid extent around the bounding box of start and goal
    max_cells : node budget: no level's grid has more cells (deterministic)
    z_min_m, z_max_m : floor and ceiling of the grid, metres (every cell centre is within)
    bounds : optional box ``(lo (3,), hi (3,))`` the grid is clipped to (a flight volume
        already shrunk by the body radius): no cell centre lies outside it
    time_budget_s : None (one level at ``resolution_m``) or a wall-time budget: levels at 4x,
        2x and 1x ``resolution_m`` run coarse to fine, and a level is not started when the
        time spent plus its predicted time (the previous level's time scaled by the cell
        count) exceeds the budget; the finest completed path is the answer (anytime)
    unknown_blocked : block cells the field reports unknown

    Returns
    -------
    GuideResult
    """
    t0 = time.perf_counter()
    lo = np.minimum(start, goal) - np.array([margin_xy_m, margin_xy_m, margin_z_m])
    hi = np.maximum(start, goal) + np.array([margin_xy_m, margin_xy_m, margin_z_m])
    if bounds is not None:
        lo = np.maximum(lo, np.asarray(bounds[0], dtype=float))
        hi = np.minimum(hi, np.asarray(bounds[1], dtype=float))
    if z_min_m is not None:
        lo[2] = max(lo[2], z_min_m)
    if z_max_m is not None:
        hi[2] = min(hi[2], z_max_m)
    hi = np.maximum(hi, lo)  # a flat (or empty) box: one layer of cells at lo
    extent = hi - lo
    finest = resolution_m
    cells = _cells(extent, finest)
    if cells > max_cells:
        finest = resolution_m * (cells / max_cells) ** (1.0 / 3.0)
        while _cells(extent, finest) > max_cells:
            finest *= 1.01
    levels = [finest] if time_budget_s is None else [4.0 * finest, 2.0 * finest, finest]
    best: np.ndarray | None = None
    best_res, best_cells, status, run = levels[0], 0, "unreachable", 0
    prev_t, prev_cells = None, None
    for res in levels:
        n_cells = _cells(extent, res)
        if time_budget_s is not None and run > 0:
            spent = time.perf_counter() - t0
            predicted = prev_t * n_cells / max(prev_cells, 1.0)
            if spent + predicted > time_budget_s:
                status = "budget"
                break
        t_level = time.perf_counter()
        path = _grid_level(field, start, goal, _lattice_through(start, lo, hi, res), hi, res, clearance_m,
                           preferred_clearance_m, unknown_blocked)
        prev_t, prev_cells = time.perf_counter() - t_level, n_cells
        run += 1
        if path is not None:
            best, best_res, best_cells, status = path, res, int(n_cells), "found"
        elif best is None:
            best_res, best_cells = res, int(n_cells)
    if status == "found" and best_res != levels[-1]:
        status = "budget"  # cannot happen without a budget: the last level always runs then
    return GuideResult(
        path=best,
        status=status,
        resolution_m=float(best_res),
        cells=best_cells,
        elapsed_ms=(time.perf_counter() - t0) * 1e3,
        levels_run=run,
    )


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
    z_max_m: float | None = None,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray | None:
    """The path of :func:`guide_search` without a time budget (array (n, 3) or None)."""
    return guide_search(
        field, start, goal, clearance_m, preferred_clearance_m, resolution_m, margin_xy_m, margin_z_m,
        max_cells, z_min_m, z_max_m, bounds,
    ).path


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
