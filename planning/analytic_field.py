"""An exact analytic distance field of primitives: the geometric ground truth.

Implements the :class:`planning.field.DistanceField` protocol for a union of boxes (optionally
yawed about z), spheres, finite vertical cylinders and half-spaces (the ground). Used by the
planner tests and benchmark as exact geometry and as a reference for the ESDF.

Exactness
---------
Each primitive's signed distance is exact. The union's field is ``min_i d_i`` with the gradient
of the minimizing primitive. Outside every primitive this *is* the exact Euclidean distance to
the union (the nearest surface point belongs to the nearest primitive). Inside overlapping
primitives it is the depth of the deepest single primitive, a lower bound on the true depth:
negative exactly where the point is inside, never positive inside. The gradient is the exact
gradient wherever the distance is differentiable; on the medial set (equidistant from two
surfaces or primitives, the centre of a box) it is the gradient of the first minimizer in the
order boxes, spheres, cylinders, half-spaces (and, within a box, the lowest axis): always a
unit vector, never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "AnalyticField",
    "Box",
    "Sphere",
    "VerticalCylinder",
    "HalfSpace",
    "AnalyticFieldError",
    "ObstacleScene",
    "SCENE_KINDS",
    "obstacle_scene",
]


class AnalyticFieldError(ValueError):
    """A primitive with invalid parameters, or query points of the wrong shape."""


def _vec3(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise AnalyticFieldError(f"{name} must be a finite (3,) vector, got {x!r}")
    return a


@dataclass(frozen=True, eq=False)
class Box:
    """Box with centre (3,) m, half extents (3,) m (> 0), rotated by ``yaw_rad`` about z."""

    center: np.ndarray
    half_extents: np.ndarray
    yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "Box.center"))
        h = _vec3(self.half_extents, "Box.half_extents")
        if np.any(h <= 0):
            raise AnalyticFieldError(f"Box.half_extents must be > 0, got {h}")
        object.__setattr__(self, "half_extents", h)
        if not np.isfinite(self.yaw_rad):
            raise AnalyticFieldError(f"Box.yaw_rad must be finite, got {self.yaw_rad}")
        object.__setattr__(self, "yaw_rad", float(self.yaw_rad))


@dataclass(frozen=True, eq=False)
class Sphere:
    """Sphere with centre (3,) m and radius m (> 0)."""

    center: np.ndarray
    radius_m: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "Sphere.center"))
        if not (np.isfinite(self.radius_m) and self.radius_m > 0):
            raise AnalyticFieldError(f"Sphere.radius_m must be > 0, got {self.radius_m}")


@dataclass(frozen=True, eq=False)
class VerticalCylinder:
    """Cylinder with vertical axis through ``center_xy`` (2,) m, radius m, from z_min to z_max."""

    center_xy: np.ndarray
    radius_m: float
    z_min_m: float
    z_max_m: float

    def __post_init__(self) -> None:
        c = np.asarray(self.center_xy, dtype=float).reshape(-1)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise AnalyticFieldError(f"VerticalCylinder.center_xy must be (2,), got {self.center_xy!r}")
        object.__setattr__(self, "center_xy", c)
        if not (np.isfinite(self.radius_m) and self.radius_m > 0):
            raise AnalyticFieldError(f"VerticalCylinder.radius_m must be > 0, got {self.radius_m}")
        if not (np.isfinite(self.z_min_m) and np.isfinite(self.z_max_m) and self.z_max_m > self.z_min_m):
            raise AnalyticFieldError(
                f"VerticalCylinder needs finite z_min_m < z_max_m, got {self.z_min_m}, {self.z_max_m}"
            )


@dataclass(frozen=True, eq=False)
class HalfSpace:
    """Solid half-space ``{x : n . (x - point) <= 0}``; free side along the normal ``n``.

    The ground is ``HalfSpace(point=(0, 0, 0), normal=(0, 0, 1))``.
    """

    point: np.ndarray
    normal: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "point", _vec3(self.point, "HalfSpace.point"))
        n = _vec3(self.normal, "HalfSpace.normal")
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            raise AnalyticFieldError("HalfSpace.normal must be nonzero")
        object.__setattr__(self, "normal", n / norm)


def _box_local(P: np.ndarray, c: np.ndarray, cos_y: np.ndarray, sin_y: np.ndarray):
    """Point offsets in the frames of boxes: (..., 3) -> lx, ly, lz, broadcast over boxes."""
    dx = P[..., 0] - c[..., 0]
    dy = P[..., 1] - c[..., 1]
    dz = P[..., 2] - c[..., 2]
    return cos_y * dx + sin_y * dy, -sin_y * dx + cos_y * dy, dz


def _box_dist(P: np.ndarray, c: np.ndarray, h: np.ndarray, cos_y: np.ndarray, sin_y: np.ndarray) -> np.ndarray:
    """Signed distance (m, n) of m boxes at n points."""
    lx, ly, lz = _box_local(P[None, :, :], c[:, None, :], cos_y[:, None], sin_y[:, None])
    qx = np.abs(lx) - h[:, 0:1]
    qy = np.abs(ly) - h[:, 1:2]
    qz = np.abs(lz) - h[:, 2:3]
    ox, oy, oz = np.maximum(qx, 0.0), np.maximum(qy, 0.0), np.maximum(qz, 0.0)
    return np.sqrt(ox * ox + oy * oy + oz * oz) + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0.0)


def _box_grad(P: np.ndarray, c: np.ndarray, h: np.ndarray, cos_y: np.ndarray, sin_y: np.ndarray) -> np.ndarray:
    """Gradient (k, 3) of box k (parameters (k, ...)) at point k (k, 3): paired, not crossed."""
    lx, ly, lz = _box_local(P, c, cos_y, sin_y)
    loc = np.stack([lx, ly, lz], axis=1)
    sgn = np.where(loc >= 0.0, 1.0, -1.0)
    q = np.abs(loc) - h
    qpos = np.maximum(q, 0.0)
    outside = np.sqrt(np.sum(qpos * qpos, axis=1))
    is_out = outside > 0.0
    g = sgn * qpos / np.where(is_out, outside, 1.0)[:, None]
    if not np.all(is_out):
        inside = ~is_out
        axis = np.argmax(q[inside], axis=1)
        gi = np.zeros((axis.size, 3))
        gi[np.arange(axis.size), axis] = sgn[inside][np.arange(axis.size), axis]
        g[inside] = gi
    gx = cos_y * g[:, 0] - sin_y * g[:, 1]
    gy = sin_y * g[:, 0] + cos_y * g[:, 1]
    g[:, 0], g[:, 1] = gx, gy
    return g


def _sphere_dist(P: np.ndarray, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    d = P[None, :, :] - c[:, None, :]
    return np.sqrt(np.einsum("mnk,mnk->mn", d, d)) - r[:, None]


def _sphere_grad(P: np.ndarray, c: np.ndarray) -> np.ndarray:
    d = P - c
    n = np.linalg.norm(d, axis=1)
    safe = n > 1e-12
    out = np.zeros_like(d)
    out[:, 0] = 1.0
    out[safe] = d[safe] / n[safe, None]
    return out


def _cylinder_dist(P: np.ndarray, cxy: np.ndarray, r: np.ndarray, zc: np.ndarray, hz: np.ndarray) -> np.ndarray:
    dx = P[None, :, 0] - cxy[:, 0:1]
    dy = P[None, :, 1] - cxy[:, 1:2]
    q_r = np.sqrt(dx * dx + dy * dy) - r[:, None]
    q_z = np.abs(P[None, :, 2] - zc[:, None]) - hz[:, None]
    o_r, o_z = np.maximum(q_r, 0.0), np.maximum(q_z, 0.0)
    return np.sqrt(o_r * o_r + o_z * o_z) + np.minimum(np.maximum(q_r, q_z), 0.0)


def _cylinder_grad(P: np.ndarray, cxy: np.ndarray, r: np.ndarray, zc: np.ndarray, hz: np.ndarray) -> np.ndarray:
    dxy = P[:, 0:2] - cxy
    rho = np.linalg.norm(dxy, axis=1)
    safe = rho > 1e-12
    radial = np.zeros_like(dxy)
    radial[:, 0] = 1.0
    radial[safe] = dxy[safe] / rho[safe, None]
    dz = P[:, 2] - zc
    sz = np.where(dz >= 0.0, 1.0, -1.0)
    q_r = rho - r
    q_z = np.abs(dz) - hz
    o_r, o_z = np.maximum(q_r, 0.0), np.maximum(q_z, 0.0)
    outside = np.hypot(o_r, o_z)
    is_out = outside > 0.0
    den = np.where(is_out, outside, 1.0)
    w_r = np.where(is_out, o_r / den, (q_r >= q_z).astype(float))
    w_z = np.where(is_out, o_z / den, (q_z > q_r).astype(float))
    return np.concatenate([radial * w_r[:, None], (sz * w_z)[:, None]], axis=1)


@dataclass(frozen=True, eq=False)
class AnalyticField:
    """Union of primitives with exact signed distance and gradient (see module docstring).

    Parameters
    ----------
    boxes, spheres, cylinders, half_spaces : sequences of the primitive dataclasses
    """

    boxes: tuple = field(default_factory=tuple)
    spheres: tuple = field(default_factory=tuple)
    cylinders: tuple = field(default_factory=tuple)
    half_spaces: tuple = field(default_factory=tuple)

    def __post_init__(self) -> None:
        kinds = (("boxes", Box), ("spheres", Sphere), ("cylinders", VerticalCylinder), ("half_spaces", HalfSpace))
        for name, cls in kinds:
            items = tuple(getattr(self, name))
            for it in items:
                if not isinstance(it, cls):
                    raise AnalyticFieldError(f"{name} must hold {cls.__name__} items, got {type(it).__name__}")
            object.__setattr__(self, name, items)
        if not (self.boxes or self.spheres or self.cylinders or self.half_spaces):
            raise AnalyticFieldError("an AnalyticField needs at least one primitive")
        # packed arrays for vectorized queries
        b = self.boxes
        self._set("_bc", np.array([x.center for x in b]).reshape(-1, 3))
        self._set("_bh", np.array([x.half_extents for x in b]).reshape(-1, 3))
        self._set("_bcos", np.cos([x.yaw_rad for x in b]).reshape(-1))
        self._set("_bsin", np.sin([x.yaw_rad for x in b]).reshape(-1))
        self._set("_sc", np.array([x.center for x in self.spheres]).reshape(-1, 3))
        self._set("_sr", np.array([x.radius_m for x in self.spheres], dtype=float).reshape(-1))
        c = self.cylinders
        self._set("_cxy", np.array([x.center_xy for x in c]).reshape(-1, 2))
        self._set("_cr", np.array([x.radius_m for x in c], dtype=float).reshape(-1))
        self._set("_czc", np.array([0.5 * (x.z_min_m + x.z_max_m) for x in c], dtype=float).reshape(-1))
        self._set("_chz", np.array([0.5 * (x.z_max_m - x.z_min_m) for x in c], dtype=float).reshape(-1))
        self._set("_hp", np.array([x.point for x in self.half_spaces]).reshape(-1, 3))
        self._set("_hn", np.array([x.normal for x in self.half_spaces]).reshape(-1, 3))
        counts = [len(self.boxes), len(self.spheres), len(self.cylinders)]
        self._set("_offsets", np.concatenate([[0], np.cumsum(counts)]).astype(int))

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance and gradient at ``points``.

        Parameters
        ----------
        points : array (n, 3), metres, world ENU (a single (3,) point is accepted too)

        Returns
        -------
        dist : array (n,), metres, positive in free space
        grad : array (n, 3), unit vectors pointing away from the nearest surface
        """
        P = np.asarray(points, dtype=float)
        if P.ndim == 1 and P.shape == (3,):
            P = P[None, :]
        if P.ndim != 2 or P.shape[1] != 3:
            raise AnalyticFieldError(f"points must have shape (n, 3), got {np.shape(points)}")
        if not np.all(np.isfinite(P)):
            raise AnalyticFieldError("points contain NaN or inf")
        parts = []
        if len(self._bc):
            parts.append(_box_dist(P, self._bc, self._bh, self._bcos, self._bsin))
        if len(self._sc):
            parts.append(_sphere_dist(P, self._sc, self._sr))
        if len(self._cxy):
            parts.append(_cylinder_dist(P, self._cxy, self._cr, self._czc, self._chz))
        if len(self._hp):
            parts.append(self._hn @ P.T - np.sum(self._hn * self._hp, axis=1)[:, None])
        D = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)
        cols = np.arange(P.shape[0])
        i = np.argmin(D, axis=0)
        dist = D[i, cols]
        grad = np.empty((P.shape[0], 3))
        o = self._offsets
        sel = (i < o[1])
        if sel.any():
            j = i[sel]
            grad[sel] = _box_grad(P[sel], self._bc[j], self._bh[j], self._bcos[j], self._bsin[j])
        sel = (i >= o[1]) & (i < o[2])
        if sel.any():
            j = i[sel] - o[1]
            grad[sel] = _sphere_grad(P[sel], self._sc[j])
        sel = (i >= o[2]) & (i < o[3])
        if sel.any():
            j = i[sel] - o[2]
            grad[sel] = _cylinder_grad(P[sel], self._cxy[j], self._cr[j], self._czc[j], self._chz[j])
        sel = i >= o[3]
        if sel.any():
            grad[sel] = self._hn[i[sel] - o[3]]
        return dist, grad

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance only, shape (n,)."""
        return self.query(points)[0]


# ---------------------------------------------------------------------------- seeded scenes
#: Kinds of seeded obstacle scenes :func:`obstacle_scene` builds.
SCENE_KINDS = ("wall", "pillars", "gap", "overhang")


@dataclass(frozen=True, eq=False)
class ObstacleScene:
    """A seeded planning problem over exact geometry.

    Attributes
    ----------
    kind : one of :data:`SCENE_KINDS`
    seed : the seed it was built from
    field : AnalyticField, the obstacles (always including the ground ``z = 0``)
    start : array (3,), start position, metres, world ENU (at rest)
    start_yaw : float, radians
    goal : array (3,), goal position, metres, world ENU
    """

    kind: str
    seed: int
    field: AnalyticField
    start: np.ndarray
    start_yaw: float
    goal: np.ndarray


_GROUND = HalfSpace(point=np.zeros(3), normal=np.array([0.0, 0.0, 1.0]))


def obstacle_scene(kind: str, seed: int, clearance_m: float = 0.45) -> ObstacleScene:
    """Build a seeded scene of one kind. Every scene has a path with clearance
    ``clearance_m + 0.15`` from start to goal that a local planner can find (no dead ends):

    - ``wall``: a (yawed) wall across the straight line, ending 0.3-1.5 m past it; go around.
    - ``pillars``: 4-12 vertical cylinders between start and goal, surfaces at least
      ``2 clearance_m + 0.3`` apart, none within ``clearance_m + 0.3`` of start or goal.
    - ``gap``: a wall across the line with a gap 1.3-2.0 m wide whose centre is offset from
      the line by up to 0.4 m; fly through.
    - ``overhang``: a wide slab whose underside is below the straight line; fly under it.

    Parameters
    ----------
    kind : one of :data:`SCENE_KINDS`
    seed : int, the only source of randomness
    clearance_m : the planner's safety distance the scene is designed for
    """
    if kind not in SCENE_KINDS:
        raise AnalyticFieldError(f"scene kind must be one of {SCENE_KINDS}, got {kind!r}")
    rng = np.random.default_rng([seed, SCENE_KINDS.index(kind)])
    length = rng.uniform(5.0, 8.0)
    heading = rng.uniform(-np.pi, np.pi)
    R = np.array([[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]])
    z0 = rng.uniform(1.0, 1.6)
    origin_xy = rng.uniform(-20.0, 20.0, size=2)
    start_l = np.array([0.0, 0.0])
    goal_l = np.array([length, rng.uniform(-0.5, 0.5)])
    boxes: list[Box] = []
    cylinders: list[VerticalCylinder] = []
    z_start, z_goal = z0, z0 + rng.uniform(-0.2, 0.2)

    def world_xy(pl: np.ndarray) -> np.ndarray:
        return origin_xy + R @ pl

    if kind == "wall":
        x_w = rng.uniform(0.35, 0.65) * length
        side = rng.choice([-1.0, 1.0])
        overlap = rng.uniform(0.3, 1.5)  # how far the wall reaches past the straight line
        extent = rng.uniform(2.0, 4.0)
        y_lo, y_hi = (-extent, overlap) if side > 0 else (-overlap, extent)
        tilt = rng.uniform(-0.3, 0.3)
        centre = world_xy(np.array([x_w, 0.5 * (y_lo + y_hi)]))
        boxes.append(
            Box(np.array([*centre, 1.5]), np.array([0.1, 0.5 * (y_hi - y_lo), 1.5]), heading + tilt)
        )
    elif kind == "pillars":
        count = int(rng.integers(4, 13))
        placed: list[tuple[np.ndarray, float]] = []
        min_gap = 2.0 * clearance_m + 0.3
        for _ in range(400):
            if len(placed) >= count:
                break
            c = np.array([rng.uniform(1.0, length - 1.0), rng.uniform(-1.5, 1.5)])
            r = rng.uniform(0.1, 0.35)
            if np.linalg.norm(c - start_l) < r + clearance_m + 0.3 or np.linalg.norm(c - goal_l) < r + clearance_m + 0.3:
                continue
            if any(np.linalg.norm(c - q) - r - rq < min_gap for q, rq in placed):
                continue
            placed.append((c, r))
        for c, r in placed:
            cylinders.append(VerticalCylinder(world_xy(c), r, 0.0, 4.0))
    elif kind == "gap":
        x_w = rng.uniform(0.35, 0.65) * length
        width = rng.uniform(1.3, 2.0)
        offset = rng.uniform(-0.4, 0.4)
        tilt = rng.uniform(-0.25, 0.25)
        for sgn in (-1.0, 1.0):
            inner = offset + sgn * 0.5 * width
            outer = offset + sgn * (0.5 * width + 4.0)
            centre_l = np.array([x_w, 0.5 * (inner + outer)])
            # rotate the wall about the gap centre by the tilt
            Rt = np.array([[np.cos(tilt), -np.sin(tilt)], [np.sin(tilt), np.cos(tilt)]])
            c_gap = np.array([x_w, offset])
            centre_l = c_gap + Rt @ (centre_l - c_gap)
            boxes.append(Box(np.array([*world_xy(centre_l), 2.0]), np.array([0.1, 2.0, 2.0]), heading + tilt))
    else:  # overhang
        z_start = rng.uniform(1.5, 1.9)
        z_goal = rng.uniform(0.8, 1.0)
        x0, x1 = rng.uniform(0.3, 0.45) * length, rng.uniform(0.6, 0.75) * length
        under = rng.uniform(1.55, 1.8)  # slab underside, metres above ground
        centre = world_xy(np.array([0.5 * (x0 + x1), 0.0]))
        boxes.append(Box(np.array([*centre, under + 1.0]), np.array([0.5 * (x1 - x0), 6.0, 1.0]), heading))
    field = AnalyticField(boxes=tuple(boxes), cylinders=tuple(cylinders), half_spaces=(_GROUND,))
    start = np.array([*world_xy(start_l), z_start])
    goal = np.array([*world_xy(goal_l), z_goal])
    return ObstacleScene(
        kind=kind,
        seed=int(seed),
        field=field,
        start=start,
        start_yaw=float(rng.uniform(-np.pi, np.pi)),
        goal=goal,
    )
