"""The task checker: proves every task solvable and its goal visible, and records the reference.

For each scene, :class:`FreeSpace` samples the exact distance from voxel centres to the scene's
triangles (Open3D ``RaycastingScene.compute_distance``) over the flight volume (the scene bounds
shrunk by ``bounds_margin_m``, altitudes ``z_min_m..z_max_m``). Voxels with clearance at least
``required_clearance_m`` (body radius + ``clearance_margin_m``) are free; 26-connected free
voxels form a graph whose edge cost is the (vertically weighted) length, raised where the
clearance is below ``preferred_clearance_m`` so routes keep to the middle of passages.

For each task:

1. the start must have clearance ``>= body_radius_m + proof_margin_m`` and a free voxel in
   reach; Dijkstra (``scipy.sparse.csgraph``) from it;
2. each via object is passed at the cheapest reachable free voxel that comes (nearly) as close to
   the object's bounds as any reachable voxel in line of sight of it, within ``via_radius_m``;
   the goal likewise, within ``max_goal_gap_m`` of the goal region (in line of sight of its goal
   object, when it has one): that voxel is the *goal point*;
3. each leg's voxel path is shortened by string pulling, where a shortcut is taken only if the
   exact mesh distance along it stays above ``min(preferred, the clearance of the voxel path it
   replaces)``: the reference follows passages like the grid path but without its staircase;
4. **proof**: the final polyline, sampled every ``path_sample_m``, keeps an exact distance to
   every triangle of at least ``body_radius_m + proof_margin_m`` and stays inside the bounds;
5. **visibility**: every target is seen from some path point: a ray from the point to a sample
   of the target's surface (within ``visibility_range_m``, within the camera's vertical half
   field of view ``vfov_half_deg`` of a level camera; yaw is free) hits that target first (the
   goal point and via points see their objects by step 2: the nearest voxel could otherwise be
   in the next room, behind a thin wall the object stands against);
6. the reference is no longer than ``max_path_m`` (30 m: 50 s at the paper's 0.6 m/s, leaving
   20 s of a 70 s episode for turns, decisions and the stop), and the goal
   region is at least ``min_goal_distance_m`` from the start.

The result, a :class:`onfly.bench.tasks.Reference` per task, is written into the task files
by ``onfly tasks check --write``.

A tracking task (``kind = "track"``) is proved differently (:meth:`TaskChecker.check_track`):

1. the start has clearance ``>= body_radius_m + proof_margin_m`` from the scene and from every
   actor at ``t = 0``, lies in the bounds, and is in the task's distance band of the followed
   actor at ``t = 0``, which is in view from it (a ray from the start to the actor's chest
   hits the actor first, every other actor at its ``t = 0`` pose occluding);
2. a *kinematic follower* flies the task: every ``track_dt_s`` it heads for the point at the
   middle of the band from the actor (``track_lead_s`` ahead) on the line toward it, with the
   vehicle's speed and acceleration limits (``track_v_max_mps``, ``track_a_max_mps2``, the
   paper's 0.6 m/s and 0.6 m/s^2), at the start's altitude; where the task asks for a stop, it
   closes to ``stop_radius_m - 0.5`` once the actor has walked and stands again;
3. **proof**: that flight keeps ``>= body_radius_m + proof_margin_m`` from the scene and from
   every actor at each instant, stays in the bounds, is in the band for at least the task's
   ``in_band_frac`` of ``duration_s``, and, for a stop task, ends within the stop radius of the
   standing actor.

Its reference is that flight (every second), its length, its end as the goal point and the start
as ``visible_from_m``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import open3d as o3d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from onfly.bench.metrics import GoalRegion
from onfly.bench.tasks import Reference, Task, object_bounds
from onfly.world.geometry import SceneGeometry
from onfly.world.scene import Scene, load_scene, resolve_scene

__all__ = ["CheckerConfig", "CheckResult", "FreeSpace", "TaskChecker", "check_tasks", "path_clearance", "polyline_length", "goal_target"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CheckerConfig:
    """Parameters of the checker (metres unless stated).

    voxel_m : search grid spacing
    body_radius_m : the vehicle's collision radius (world default 0.25)
    clearance_margin_m : free voxels need ``body_radius_m +`` this (0.25: the planner's
        d_safe 0.45 plus 5 cm, so the oracle's MPC can follow the reference)
    proof_margin_m : the final polyline's exact clearance must be ``>= body_radius_m +`` this
    preferred_clearance_m, clearance_cost : edge cost factor ``1 + clearance_cost *
        (preferred - c) / preferred`` below the preferred clearance
    vertical_cost : weight on the vertical component of an edge's length
    z_min_m, z_max_m : altitude band searched; bounds_margin_m : distance kept from the bounds
    approach_slack_m : a goal / via voxel may be this much farther from its box than the closest
        reachable voxel (the cheapest of those is taken)
    max_goal_gap_m : the goal point must be within this of the goal region
    via_radius_m : the route must pass within this of each via object
    visibility_range_m : D_max of the camera for the visibility test
    vfov_half_deg : half the vertical field of view (level camera), minus a safety margin
    visibility_samples : surface samples per target
    path_sample_m : spacing of the exact clearance samples along the path
    visibility_step_m : spacing of the path points used for the visibility test
    min_goal_distance_m : least straight-line distance from the start to the goal region
    max_path_m : longest admissible reference path, metres (step 6)
    seed : seeds the surface samples
    """

    voxel_m: float = 0.3
    body_radius_m: float = 0.25
    clearance_margin_m: float = 0.25
    proof_margin_m: float = 0.1
    preferred_clearance_m: float = 1.2
    clearance_cost: float = 1.0
    vertical_cost: float = 1.5
    z_min_m: float = 0.6
    z_max_m: float = 5.4
    bounds_margin_m: float = 0.5
    approach_slack_m: float = 0.5
    max_goal_gap_m: float = 1.5
    via_radius_m: float = 2.5
    visibility_range_m: float = 7.0
    vfov_half_deg: float = 28.0
    visibility_samples: int = 300
    path_sample_m: float = 0.05
    visibility_step_m: float = 0.5
    min_goal_distance_m: float = 7.0
    max_path_m: float = 30.0
    seed: int = 0
    track_dt_s: float = 0.1
    track_v_max_mps: float = 0.6
    track_a_max_mps2: float = 0.6
    track_lead_s: float = 1.0

    def __post_init__(self) -> None:
        positive = (
            "voxel_m", "body_radius_m", "proof_margin_m", "preferred_clearance_m", "vertical_cost",
            "max_goal_gap_m", "via_radius_m", "visibility_range_m", "vfov_half_deg", "path_sample_m",
            "visibility_step_m", "max_path_m",
        )
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"CheckerConfig.{name} must be positive and finite, got {v!r}")
        for name in ("clearance_margin_m", "clearance_cost", "approach_slack_m", "bounds_margin_m", "min_goal_distance_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"CheckerConfig.{name} must be >= 0 and finite, got {v!r}")
        if self.z_max_m <= self.z_min_m:
            raise ValueError(f"CheckerConfig.z_max_m must exceed z_min_m, got {self.z_min_m}..{self.z_max_m}")
        if self.proof_margin_m > self.clearance_margin_m:
            raise ValueError("CheckerConfig.proof_margin_m must not exceed clearance_margin_m")
        if not (isinstance(self.visibility_samples, int) and self.visibility_samples >= 1):
            raise ValueError(f"CheckerConfig.visibility_samples must be a positive int, got {self.visibility_samples!r}")

    @property
    def required_clearance_m(self) -> float:
        return self.body_radius_m + self.clearance_margin_m


@dataclass(frozen=True, eq=False)
class CheckResult:
    """Outcome for one task: ``ok`` with a Reference, or the problems that make it unsolvable.
    ``straight_distance_m``: the straight line from the start to the goal region's nearest
    point, metres (the reference path ends within ``max_goal_gap_m`` of the region, so it can
    be the shorter of the two)."""

    task_id: str
    ok: bool
    problems: tuple[str, ...]
    reference: Reference | None
    straight_distance_m: float = float("nan")
    stats: dict = field(default_factory=dict)


def polyline_length(points: np.ndarray) -> float:
    """Length of a polyline (k, 3), metres."""
    P = np.asarray(points, float)
    return float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1))) if len(P) > 1 else 0.0


def densify(points: np.ndarray, step_m: float) -> np.ndarray:
    """Points along a polyline (k, 3) spaced at most ``step_m`` apart (vertices included)."""
    P = np.asarray(points, float)
    out = [P[:1]]
    for a, b in zip(P[:-1], P[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step_m)))
        s = np.arange(1, n + 1)[:, None] / n
        out.append(a + s * (b - a))
    return np.vstack(out)


def path_clearance(geometry: SceneGeometry, points: np.ndarray, step_m: float = 0.05) -> float:
    """Smallest exact distance (metres) from a polyline (k, 3) to the scene's triangles."""
    return float(geometry.closest(densify(points, step_m))[0].min())


def goal_target(task: Task) -> str:
    """The object whose visibility anchors the goal: the goal object, else the last target."""
    return task.goal.object if task.goal.object is not None else task.targets[-1]


_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)])


class FreeSpace:
    """Exact clearance on a voxel lattice of one scene and the graph of its free voxels.

    Attributes
    ----------
    origin_m : (3,), centre of voxel (0, 0, 0); shape : (nx, ny, nz)
    clearance_m : float32 (nx, ny, nz), exact distance from each voxel centre to the triangles
    free : bool (nx, ny, nz), clearance >= required
    """

    def __init__(self, geometry: SceneGeometry, config: CheckerConfig) -> None:
        self.geometry = geometry
        self.config = c = config
        b = geometry.scene.bounds
        lo = b.min_m + c.bounds_margin_m
        hi = b.max_m - c.bounds_margin_m
        lo[2] = max(lo[2], c.z_min_m)
        hi[2] = min(hi[2], c.z_max_m)
        if np.any(hi <= lo):
            raise ValueError(f"scene {geometry.scene.name!r}: empty flight volume {lo.tolist()}..{hi.tolist()}")
        self.origin_m = lo
        self.shape = tuple(int(n) for n in np.floor((hi - lo) / c.voxel_m).astype(int) + 1)
        centers = self.centers(np.arange(int(np.prod(self.shape))))
        dist = geometry.raycasting.compute_distance(o3d.core.Tensor(centers.astype(np.float32)), nthreads=0).numpy()
        self.clearance_m = dist.reshape(self.shape)
        self.free = self.clearance_m >= c.required_clearance_m
        self.graph = self._graph()

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def centers(self, nodes: np.ndarray) -> np.ndarray:
        """World positions (n, 3) of flat voxel indices (n,)."""
        ijk = np.stack(np.unravel_index(np.asarray(nodes), self.shape), axis=-1)
        return self.origin_m + ijk * self.config.voxel_m

    def _graph(self):
        c = self.config
        nx, ny, nz = self.shape
        idx = np.arange(self.size).reshape(self.shape)
        rows, cols, w = [], [], []
        clr = np.minimum(self.clearance_m, c.preferred_clearance_m)
        for off in _OFFSETS:
            sa = tuple(slice(max(0, -o), n - max(0, o)) for o, n in zip(off, self.shape))
            sb = tuple(slice(max(0, o), n - max(0, -o)) for o, n in zip(off, self.shape))
            ok = self.free[sa] & self.free[sb]
            if not ok.any():
                continue
            length = c.voxel_m * math.sqrt(off[0] ** 2 + off[1] ** 2 + (c.vertical_cost * off[2]) ** 2)
            cmin = np.minimum(clr[sa], clr[sb])[ok]
            rows.append(idx[sa][ok])
            cols.append(idx[sb][ok])
            w.append(length * (1.0 + c.clearance_cost * (c.preferred_clearance_m - cmin) / c.preferred_clearance_m))
        r = np.concatenate(rows)
        k = np.concatenate(cols)
        return coo_matrix((np.concatenate(w), (r, k)), shape=(self.size, self.size)).tocsr()

    def nearest_free(self, p: np.ndarray, radius_m: float) -> int | None:
        """Flat index of the free voxel nearest to ``p`` (3,) within ``radius_m``, or None."""
        c = self.config
        r = int(math.ceil(radius_m / c.voxel_m))
        ijk0 = np.round((np.asarray(p, float) - self.origin_m) / c.voxel_m).astype(int)
        lo = np.maximum(ijk0 - r, 0)
        hi = np.minimum(ijk0 + r + 1, self.shape)
        if np.any(hi <= lo):
            return None
        sub = self.free[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        cand = np.argwhere(sub) + lo
        if len(cand) == 0:
            return None
        pts = self.origin_m + cand * c.voxel_m
        d = np.linalg.norm(pts - p, axis=1)
        i = int(np.argmin(d))
        if d[i] > radius_m:
            return None
        return int(np.ravel_multi_index(tuple(cand[i]), self.shape))

    def shortest(self, source: int) -> tuple[np.ndarray, np.ndarray]:
        """Dijkstra from a flat voxel index: (cost (n,), predecessor (n,), -9999 = none)."""
        cost, pred = dijkstra(self.graph, directed=False, indices=source, return_predecessors=True)
        return cost, pred

    @staticmethod
    def chain(pred: np.ndarray, source: int, target: int) -> list[int]:
        """Voxel indices from ``source`` to ``target`` along Dijkstra predecessors."""
        out = [target]
        while out[-1] != source:
            p = int(pred[out[-1]])
            if p < 0:
                raise ValueError(f"voxel {target} is not reachable from {source}")
            out.append(p)
        return out[::-1]


class TaskChecker:
    """Checks tasks of one scene; builds the free space once and caches Dijkstra trees."""

    def __init__(self, scene: Scene, config: CheckerConfig | None = None) -> None:
        self.config = config if config is not None else CheckerConfig()
        self.scene = scene
        self.geometry = SceneGeometry(scene)
        self.space = FreeSpace(self.geometry, self.config)
        self._trees: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._rng_seed = self.config.seed

    def _tree(self, node: int) -> tuple[np.ndarray, np.ndarray]:
        if node not in self._trees:
            self._trees[node] = self.space.shortest(node)
        return self._trees[node]

    def _approach(
        self, cost: np.ndarray, region: GoalRegion, max_gap_m: float, what: str, sees: str | None = None
    ) -> tuple[int | None, str]:
        """Cheapest reachable voxel nearly as close to ``region`` as any reachable voxel; with
        ``sees`` (an object's name), as any reachable voxel in line of sight of that object
        (:meth:`visible_mask` at any elevation): the nearest voxel can lie on the far side of a
        thin wall the object hangs beside."""
        reach = np.flatnonzero(np.isfinite(cost))
        if len(reach) == 0:
            return None, f"{what}: nothing reachable"
        d = region.distance(self.space.centers(reach))
        dmin = float(d.min())
        if dmin > max_gap_m:
            return None, f"{what}: the closest reachable free point is {dmin:.2f} m from it (limit {max_gap_m} m)"
        if sees is not None:
            keep = d <= max_gap_m
            reach, d = reach[keep], d[keep]
            seeing = self._seeing(reach, d, sees)
            if not seeing.any():
                return None, f"{what}: no reachable free point within {max_gap_m} m of it has a line of sight to it"
            reach, d = reach[seeing], d[seeing]
            dmin = float(d.min())
        cand = reach[d <= dmin + self.config.approach_slack_m]
        return int(cand[np.argmin(cost[cand])]), ""

    def _seeing(self, nodes: np.ndarray, d: np.ndarray, name: str, chunk: int = 256) -> np.ndarray:
        """bool per node: in line of sight of ``name``. Tested nearest first (``d``, metres from
        the object), and only up to ``approach_slack_m`` beyond the nearest one that sees it:
        no farther node can be a candidate of :meth:`_approach`."""
        order = np.argsort(d, kind="stable")
        out = np.zeros(len(nodes), dtype=bool)
        limit = np.inf
        for k in range(0, len(order), chunk):
            idx = order[k : k + chunk]
            idx = idx[d[idx] <= limit]
            if len(idx) == 0:
                break
            out[idx] = self.visible_mask(self.space.centers(nodes[idx]), name, level_camera=False)
            if out[idx].any() and not np.isfinite(limit):
                limit = float(d[idx][out[idx]].min()) + self.config.approach_slack_m
        return out

    def _smooth(self, pts: np.ndarray) -> np.ndarray:
        """String pulling with exact clearance checks (see the module docstring)."""
        c = self.config
        if len(pts) <= 2:
            return pts
        clr = self.geometry.closest(pts)[0]
        out = [0]
        i = 0
        n = len(pts)
        while i < n - 1:
            best = i + 1
            floor_m = clr[i]
            j = i + 1
            # extend while the shortcut keeps the clearance of the stretch it replaces
            while j < n:
                floor_m = min(floor_m, clr[j])
                need = max(c.body_radius_m + c.proof_margin_m, min(c.preferred_clearance_m, floor_m) - 1e-6)
                seg = densify(pts[[i, j]], c.path_sample_m)
                if self.geometry.closest(seg)[0].min() >= need:
                    best = j
                    j += 1
                else:
                    # a longer shortcut may still pass; try a few more before giving up
                    look = j + 1
                    found = False
                    while look < min(n, j + 4):
                        floor_m = min(floor_m, clr[look])
                        need = max(c.body_radius_m + c.proof_margin_m, min(c.preferred_clearance_m, floor_m) - 1e-6)
                        if self.geometry.closest(densify(pts[[i, look]], c.path_sample_m))[0].min() >= need:
                            best, j, found = look, look + 1, True
                            break
                        look += 1
                    if not found:
                        break
            out.append(best)
            i = best
        return pts[out]

    def _surface_samples(self, name: str) -> np.ndarray:
        """Points (k, 3) spread over the target's triangles by area (seeded), plus its vertices."""
        iid = self.scene.object_by_name(name).instance_id
        g = self.geometry
        tri = g.triangles[g.tri_instance == iid]
        V = g.vertices[tri].astype(float)  # (m, 3, 3)
        area = 0.5 * np.linalg.norm(np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0]), axis=1)
        rng = np.random.default_rng([self._rng_seed, iid])
        k = self.config.visibility_samples
        pick = rng.choice(len(V), size=k, p=area / area.sum()) if area.sum() > 0 else rng.integers(0, len(V), k)
        u, v = rng.random(k), rng.random(k)
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        T = V[pick]
        pts = T[:, 0] + u[:, None] * (T[:, 1] - T[:, 0]) + v[:, None] * (T[:, 2] - T[:, 0])
        centroid = V.mean(axis=1)
        return np.vstack([pts, centroid[: max(1, k // 3)]])

    def visible_mask(self, path_points: np.ndarray, name: str, level_camera: bool = True) -> np.ndarray:
        """bool (n,): from which path points (n, 3) the named object is in view (see step 5).
        ``level_camera=False``: in line of sight at any elevation (a camera free to pitch)."""
        c = self.config
        iid = self.scene.object_by_name(name).instance_id
        Q = self._surface_samples(name)
        P = np.asarray(path_points, float)
        D = Q[None, :, :] - P[:, None, :]  # (n, k, 3)
        dist = np.linalg.norm(D, axis=2)
        horiz = np.linalg.norm(D[..., :2], axis=2)
        elev = np.degrees(np.arctan2(np.abs(D[..., 2]), horiz))
        ok = (dist <= c.visibility_range_m) & (dist > 1e-6)
        if level_camera:
            ok &= elev <= c.vfov_half_deg
        vis = np.zeros(len(P), dtype=bool)
        ii, kk = np.nonzero(ok)
        if len(ii) == 0:
            return vis
        dirs = D[ii, kk] / dist[ii, kk, None]
        rays = np.hstack([P[ii], dirs]).astype(np.float32)
        hits = self.geometry.cast(rays, threads=0)
        tri = hits["primitive_ids"].astype(np.int64)
        hit = tri < self.geometry.triangle_count
        inst = np.where(hit, self.geometry.tri_instance[np.minimum(tri, self.geometry.triangle_count - 1)], 0)
        seen = inst == iid
        vis[np.unique(ii[seen])] = True
        return vis

    def check(self, task: Task) -> CheckResult:
        """Prove one task solvable (see the module docstring); never raises for a bad task."""
        if task.track is not None:
            return self.check_track(task)
        c = self.config
        problems: list[str] = []
        region = task.goal_region
        start = task.start.position_m.astype(float)
        straight = float(region.distance(start))
        if straight < c.min_goal_distance_m:
            problems.append(f"goal region only {straight:.1f} m from the start (need >= {c.min_goal_distance_m} m)")
        start_clear = float(self.geometry.closest(start[None])[0][0])
        if start_clear < c.body_radius_m + c.proof_margin_m:
            problems.append(f"start has clearance {start_clear:.2f} m (< body radius {c.body_radius_m} + {c.proof_margin_m})")
            return CheckResult(task.task_id, False, tuple(problems), None, straight)
        node = self.space.nearest_free(start, 2.0 * c.voxel_m)
        if node is None:
            problems.append(f"no free voxel (clearance >= {c.required_clearance_m} m) within {2 * c.voxel_m} m of the start")
            return CheckResult(task.task_id, False, tuple(problems), None, straight)
        legs: list[np.ndarray] = []
        cur = node
        # a via object is passed where it is in sight (the closest point past a banner can be
        # in the room beside the corridor it hangs in, 0.12 m of wall away)
        stops = [(f"via object {v!r}", self._via_region(v), c.via_radius_m, v) for v in task.via]
        stops.append(("goal region", region, c.max_goal_gap_m, task.goal.object))
        for what, reg, gap, sees in stops:
            cost, pred = self._tree(cur)
            nxt, why = self._approach(cost, reg, gap, what, sees)
            if nxt is None:
                problems.append(why)
                return CheckResult(task.task_id, False, tuple(problems), None, straight)
            legs.append(self.space.centers(np.array(FreeSpace.chain(pred, cur, nxt))))
            cur = nxt
        pts = [start[None]]
        for leg in legs:
            pts.append(self._smooth(np.vstack([pts[-1][-1:], leg]))[1:])
        path = np.vstack(pts)
        length = polyline_length(path)
        clear = path_clearance(self.geometry, path, c.path_sample_m)
        if clear < c.body_radius_m + c.proof_margin_m:
            problems.append(f"reference path clearance {clear:.3f} m below {c.body_radius_m + c.proof_margin_m} m")
        dense = densify(path, c.path_sample_m)
        if not np.all(self.scene.bounds.contains(dense)):
            problems.append("reference path leaves the scene bounds")
        if length > c.max_path_m:
            problems.append(f"reference path {length:.1f} m longer than {c.max_path_m} m")
        vis_pts = densify(path, c.visibility_step_m)
        visible_from = None
        for name in dict.fromkeys(task.targets + ((task.goal.object,) if task.goal.object else ())):
            mask = self.visible_mask(vis_pts, name)
            if not mask.any():
                problems.append(f"target {name!r} is not visible from any point of the reference path")
            elif name == goal_target(task):
                visible_from = vis_pts[int(np.argmax(mask))]
        ref = None
        if not problems:
            ref = Reference(length, path, path[-1].copy(), visible_from, clear)
        return CheckResult(
            task.task_id, not problems, tuple(problems), ref, straight,
            {"legs": len(legs), "goal_gap_m": float(region.distance(path[-1]))},
        )

    def check_track(self, task: Task) -> CheckResult:
        """Prove a tracking task feasible (module docstring, tracking steps 1-3)."""
        from onfly.world.actors import pose_at, poses_at

        c = self.config
        tr = task.track
        g = self.geometry
        problems: list[str] = []
        actor = self.scene.object_by_name(tr.actor)
        motion = actor.motion
        start = task.start.position_m.astype(float)
        a0 = pose_at(motion, 0.0)
        d0 = float(np.hypot(*(start[:2] - a0.position_m[:2])))
        straight = d0
        need = c.body_radius_m + c.proof_margin_m
        clear0 = float(g.closest(start[None], t_s=0.0)[0][0])
        if clear0 < need:
            problems.append(f"start has clearance {clear0:.2f} m from the scene and the actors at t = 0 (< {need:.2f})")
        if not bool(self.scene.bounds.contains(start[None])[0]):
            problems.append("start lies outside the scene bounds")
        if not (tr.band_m[0] <= d0 <= tr.band_m[1]):
            problems.append(f"start is {d0:.2f} m from {tr.actor!r} at t = 0, outside the band {list(tr.band_m)}")
        chest = a0.position_m + np.array([0.0, 0.0, 1.1])
        ray = np.hstack([start, chest - start]).astype(np.float32)[None]
        hit = g.cast(ray)
        t_hit = hit["t_hit"].astype(np.float32).copy()
        tri = hit["primitive_ids"].astype(np.int64).copy()
        g.cast_actors(ray, t_hit, tri, 0.0)
        inst = g.combined_table("tri_instance")
        seen = bool(np.isfinite(t_hit[0]) and 0 <= tri[0] < len(inst) and int(inst[tri[0]]) == actor.instance_id)
        if not seen:
            problems.append(f"{tr.actor!r} is not in view from the start at t = 0")
        # the kinematic follower
        n = int(round(tr.duration_s / c.track_dt_s))
        t = np.arange(n + 1) * c.track_dt_s
        P_now, _, _, moving = poses_at(motion, t)
        P_ahead, _, _, _ = poses_at(motion, t + c.track_lead_s)
        p = start.copy()
        v = np.zeros(3)
        path = [p.copy()]
        stopped_at = None
        for k in range(n):
            standoff = tr.standoff_m
            if tr.stop_radius_m is not None and not moving[k] and moving[:k].any():
                standoff = min(standoff, tr.stop_radius_m - 0.5)
                if float(np.hypot(*(p[:2] - P_now[k, :2]))) <= tr.stop_radius_m - 0.3 and np.linalg.norm(v) <= 0.15:
                    stopped_at = k
                    break
            away = p[:2] - P_ahead[k, :2]
            dist = float(np.hypot(*away))
            away = away / dist if dist > 1e-9 else np.array([1.0, 0.0])
            goal = np.array([*(P_ahead[k, :2] + standoff * away), start[2]])
            err = goal - p
            # brake-aware speed command toward the goal, within the speed and acceleration limits
            dist_goal = float(np.linalg.norm(err))
            v_cmd = np.zeros(3) if dist_goal < 1e-9 else err / dist_goal * min(c.track_v_max_mps, math.sqrt(2 * c.track_a_max_mps2 * dist_goal))
            dv = v_cmd - v
            dv_n = float(np.linalg.norm(dv))
            if dv_n > c.track_a_max_mps2 * c.track_dt_s:
                dv *= c.track_a_max_mps2 * c.track_dt_s / dv_n
            v = v + dv
            p = p + v * c.track_dt_s
            path.append(p.copy())
        path = np.array(path)
        tt = t[: len(path)]
        dist = np.hypot(*(path[:, :2] - P_now[: len(path), :2]).T)
        inside = (dist >= tr.band_m[0]) & (dist <= tr.band_m[1])
        horizon = tt[-1] if (tr.stop_radius_m is not None and stopped_at is not None) else tr.duration_s
        frac = float(np.sum(inside[:-1]) * c.track_dt_s / horizon) if horizon > 0 else float(inside[0])
        if frac < tr.in_band_frac:
            problems.append(f"a kinematic follower within the speed limit is in the band only {100 * frac:.0f} % of the time "
                            f"(the task asks {100 * tr.in_band_frac:.0f} %)")
        if tr.stop_radius_m is not None and stopped_at is None:
            problems.append(f"the follower does not get within the stop radius {tr.stop_radius_m} m of the standing actor in time")
        d_static = g.closest(path)[0]
        d_all = g.closest(path, t_s=tt)[0]
        clear = float(min(d_static.min(), d_all.min()))
        if clear < need:
            k = int(np.argmin(d_all))
            problems.append(f"the follower's flight comes {clear:.2f} m from the scene or an actor (t = {tt[k]:.1f} s; need {need:.2f})")
        if not np.all(self.scene.bounds.contains(path)):
            problems.append("the follower's flight leaves the scene bounds")
        ref = None
        if not problems:
            keep = np.unique(np.r_[np.arange(0, len(path), max(1, int(round(1.0 / c.track_dt_s)))), len(path) - 1])
            wp = path[keep]
            ref = Reference(polyline_length(path), wp, path[-1].copy(), start.copy(), clear)
        return CheckResult(task.task_id, not problems, tuple(problems), ref, straight,
                           {"follower_in_band": frac, "follower_stopped_s": None if stopped_at is None else float(t[stopped_at])})

    def _via_region(self, name: str) -> GoalRegion:
        lo, hi = object_bounds(self.scene, name)
        return GoalRegion((lo + hi) / 2, (hi - lo) / 2)


def check_tasks(tasks: Sequence[Task], config: CheckerConfig | None = None, progress: Any = None) -> list[CheckResult]:
    """Check tasks (grouped by scene, each scene's free space built once), in input order.

    ``progress`` (optional) is anything with ``update(n)``, e.g. a tqdm bar."""
    cfg = config if config is not None else CheckerConfig()
    by_scene: dict[str, list[int]] = {}
    for i, t in enumerate(tasks):  # an external scene by its file, a committed one by name
        by_scene.setdefault(t.scene_ref, []).append(i)
    out: list[CheckResult | None] = [None] * len(tasks)
    for scene_name, idx in by_scene.items():
        checker = TaskChecker(load_scene(resolve_scene(scene_name)), cfg)
        for i in idx:
            out[i] = checker.check(tasks[i])
            if progress is not None:
                progress.update(1)
    return [r for r in out if r is not None]
