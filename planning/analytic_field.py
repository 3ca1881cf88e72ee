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


def _box_sdf(P: np.ndarray, c: np.ndarray, h: np.ndarray, cos_y: np.ndarray, sin_y: np.ndarray):
    """Signed distance (m, n) and gradient (m, n, 3) of m boxes at n points (vectorized)."""
    d = P[None, :, :] - c[:, None, :]  # (m, n, 3) world offsets
    # rotate into box frame: local = R(yaw)^T d
    lx = cos_y[:, None] * d[..., 0] + sin_y[:, None] * d[..., 1]
    ly = -sin_y[:, None] * d[..., 0] + cos_y[:, None] * d[..., 1]
    local = np.stack([lx, ly, d[..., 2]], axis=-1)
    sgn = np.where(local >= 0, 1.0, -1.0)
    q = np.abs(local) - h[:, None, :]
    qpos = np.maximum(q, 0.0)
    outside = np.linalg.norm(qpos, axis=-1)
    qmax = q.max(axis=-1)
    dist = outside + np.minimum(qmax, 0.0)
    # gradient in the box frame
    is_out = outside > 0
    g_out = sgn * qpos / np.where(is_out, outside, 1.0)[..., None]
    axis = np.argmax(q, axis=-1)
    g_in = np.zeros_like(local)
    np.put_along_axis(g_in, axis[..., None], np.take_along_axis(sgn, axis[..., None], axis=-1), axis=-1)
    g_loc = np.where(is_out[..., None], g_out, g_in)
    gx = cos_y[:, None] * g_loc[..., 0] - sin_y[:, None] * g_loc[..., 1]
    gy = sin_y[:, None] * g_loc[..., 0] + cos_y[:, None] * g_loc[..., 1]
    return dist, np.stack([gx, gy, g_loc[..., 2]], axis=-1)


def _sphere_sdf(P: np.ndarray, c: np.ndarray, r: np.ndarray):
    d = P[None, :, :] - c[:, None, :]
    n = np.linalg.norm(d, axis=-1)
    safe = n > 1e-12
    g = np.where(safe[..., None], d / np.where(safe, n, 1.0)[..., None], np.array([1.0, 0.0, 0.0]))
    return n - r[:, None], g


def _cylinder_sdf(P: np.ndarray, cxy: np.ndarray, r: np.ndarray, zc: np.ndarray, hz: np.ndarray):
    dxy = P[None, :, :2] - cxy[:, None, :]
    rho = np.linalg.norm(dxy, axis=-1)
    safe = rho > 1e-12
    radial = np.where(safe[..., None], dxy / np.where(safe, rho, 1.0)[..., None], np.array([1.0, 0.0]))
    dz = P[None, :, 2] - zc[:, None]
    sz = np.where(dz >= 0, 1.0, -1.0)
    q_r = rho - r[:, None]
    q_z = np.abs(dz) - hz[:, None]
    out_r, out_z = np.maximum(q_r, 0.0), np.maximum(q_z, 0.0)
    outside = np.hypot(out_r, out_z)
    dist = outside + np.minimum(np.maximum(q_r, q_z), 0.0)
    is_out = outside > 0
    den = np.where(is_out, outside, 1.0)
    w_r = np.where(is_out, out_r / den, (q_r >= q_z).astype(float))
    w_z = np.where(is_out, out_z / den, (q_z > q_r).astype(float))
    g = np.concatenate([radial * w_r[..., None], (sz * w_z)[..., None]], axis=-1)
    return dist, g


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
        dists, grads = [], []
        if len(self._bc):
            d, g = _box_sdf(P, self._bc, self._bh, self._bcos, self._bsin)
            dists.append(d)
            grads.append(g)
        if len(self._sc):
            d, g = _sphere_sdf(P, self._sc, self._sr)
            dists.append(d)
            grads.append(g)
        if len(self._cxy):
            d, g = _cylinder_sdf(P, self._cxy, self._cr, self._czc, self._chz)
            dists.append(d)
            grads.append(g)
        if len(self._hp):
            d = np.einsum("mnk,mk->mn", P[None, :, :] - self._hp[:, None, :], self._hn)
            dists.append(d)
            grads.append(np.broadcast_to(self._hn[:, None, :], d.shape + (3,)))
        D = np.concatenate(dists, axis=0)
        Gr = np.concatenate(grads, axis=0)
        i = np.argmin(D, axis=0)
        cols = np.arange(P.shape[0])
        return D[i, cols], Gr[i, cols]

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance only, shape (n,)."""
        return self.query(points)[0]
