"""Motions of actors: scene objects that move (people walking a route, a person circling a
fountain).

Pure numpy, no Open3D. A *motion* says where an actor's own frame is at any time; the actor's
geometry (its parts in the scene file) is written in that frame and placed at the pose.

Frames and units
----------------
World ENU, metres, seconds on the world clock (the virtual clock both the world and the pilot
use; an episode starts at ``t = 0``), radians. The actor frame has its origin at the pose's
``position_m`` (for a person: the point on the ground between the feet), x forward (the
direction of travel), y left, z up; ``T_world_actor = [Rz(yaw) | position]``. Actors stay
upright: the pose has a yaw only.

Motions
-------
:class:`PathMotion`: straight segments between waypoints. Waypoint ``k`` carries the speed of
the segment that *starts* at it and the pause held on *arrival* at it. The actor leaves
waypoint 0 at ``start_s`` (waypoint 0's pause is held only when a loop comes back to it).
A loop closes with a segment from the last waypoint back to the first (do not repeat the first
waypoint); a one-way path ends at the last waypoint and the actor stays there (``moving``
False) for ever after. Before ``start_s`` the actor stands at waypoint 0 facing its first
segment.

:class:`CircleMotion`: constant speed on a horizontal circle, counter-clockwise seen from
above unless ``clockwise``; ``phase_rad`` is the angle of the start position about the centre
(0 = east of the centre, on +x); before ``start_s`` the actor stands at the phase angle.

Yaw is the direction of travel (``atan2`` of the horizontal velocity); during a pause, after a
one-way path ends and before the start it is held at the heading of the adjacent segment. A
purely vertical segment keeps the heading of the segment before it.

The scene format (``docs/scene_format.md``) writes a motion as a table under the object::

    [objects.motion]
    type = "path"                # or "circle"
    loop = true                  # path: default true
    start_s = 0.0                # default 0
    waypoints = [
      { position_m = [0.0, 0.0, 0.0], speed_mps = 1.3 },
      { position_m = [8.0, 0.0, 0.0], speed_mps = 1.3, pause_s = 2.0 },
    ]

    [objects.motion]
    type = "circle"
    center_m = [0.0, 0.0, 0.0]
    radius_m = 6.0
    speed_mps = 1.2
    phase_deg = 90.0             # file in degrees, phase_rad here
    clockwise = false
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Union

import numpy as np

__all__ = [
    "MotionFormatError",
    "Waypoint",
    "PathMotion",
    "CircleMotion",
    "Motion",
    "ActorPose",
    "pose_at",
    "poses_at",
    "positions_at",
    "parse_motion",
    "T_world_actor",
    "MOTION_TYPES",
]

#: Motion types of the scene format.
MOTION_TYPES = ("path", "circle")
#: Shortest segment a path may have, metres (consecutive waypoints closer than this are a typo).
MIN_SEGMENT_M = 1e-3


class MotionFormatError(ValueError):
    """A motion spec that cannot be flown: bad speed, too few waypoints, unknown field...

    Attributes
    ----------
    field : str, the field at fault relative to the motion table (``"waypoints[1].speed_mps"``)
    detail : str, what is wrong
    """

    def __init__(self, field: str | None, detail: str, where: str = "motion") -> None:
        self.field = field
        self.detail = detail
        loc = where if field is None else f"{where}.{field}"
        super().__init__(f"{loc}: {detail}")


def _finite_vec3(v: Any, field: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise MotionFormatError(field, f"expected 3 finite numbers, got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _positive(v: float, field: str) -> float:
    if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
        raise MotionFormatError(field, f"must be a finite number > 0, got {v!r}")
    return float(v)


def _nonnegative(v: float, field: str) -> float:
    if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0):
        raise MotionFormatError(field, f"must be a finite number >= 0, got {v!r}")
    return float(v)


@dataclass(frozen=True)
class Waypoint:
    """One corner of a path.

    position_m : (x, y, z) metres, world ENU, where the actor frame's origin passes
    speed_mps : m/s > 0, speed of the segment that starts here
    pause_s : s >= 0, standing time on arrival here
    """

    position_m: tuple[float, float, float]
    speed_mps: float
    pause_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_m", _finite_vec3(self.position_m, "position_m"))
        _positive(self.speed_mps, "speed_mps")
        _nonnegative(self.pause_s, "pause_s")


@dataclass(frozen=True)
class PathMotion:
    """Straight segments between waypoints at the waypoints' speeds (module docstring).

    waypoints : two or more :class:`Waypoint`; consecutive ones (and, for a loop, the last and
        the first) at least 1 mm apart
    loop : True: after the last waypoint walk back to the first and repeat; False: stop at
        the last one
    start_s : s, world-clock time the actor leaves waypoint 0
    """

    waypoints: tuple[Waypoint, ...]
    loop: bool = True
    start_s: float = 0.0

    def __post_init__(self) -> None:
        wps = tuple(self.waypoints)
        object.__setattr__(self, "waypoints", wps)
        if len(wps) < 2:
            raise MotionFormatError("waypoints", f"a path needs at least 2 waypoints, got {len(wps)}")
        for i, w in enumerate(wps):
            if not isinstance(w, Waypoint):
                raise MotionFormatError(f"waypoints[{i}]", f"expected a Waypoint, got {type(w).__name__}")
        if not (isinstance(self.start_s, (int, float)) and math.isfinite(self.start_s)):
            raise MotionFormatError("start_s", f"must be a finite number, got {self.start_s!r}")
        P = np.array([w.position_m for w in wps])
        n_seg = len(wps) if self.loop else len(wps) - 1
        for k in range(n_seg):
            d = float(np.linalg.norm(P[(k + 1) % len(wps)] - P[k]))
            if d < MIN_SEGMENT_M:
                j = (k + 1) % len(wps)
                hint = " (a loop closes by itself: do not repeat the first waypoint)" if j == 0 else ""
                raise MotionFormatError(f"waypoints[{j}]", f"coincides with waypoints[{k}] ({d:.4f} m apart){hint}")

    @cached_property
    def _timeline(self) -> dict[str, np.ndarray | float]:
        """Segment table: start point (K, 3), unit direction (K, 3), speed (K,), duration (K,),
        start time relative to ``start_s`` (K,), heading (K,), end point (K, 3); cycle length."""
        wps = self.waypoints
        n = len(wps)
        K = n if self.loop else n - 1
        P = np.array([w.position_m for w in wps], dtype=float)
        p0 = P[:K]
        p1 = P[(np.arange(K) + 1) % n]
        delta = p1 - p0
        length = np.linalg.norm(delta, axis=1)
        direction = delta / length[:, None]
        speed = np.array([wps[k].speed_mps for k in range(K)], dtype=float)
        duration = length / speed
        pause = np.array([wps[(k + 1) % n].pause_s for k in range(K)], dtype=float)
        seg_start = np.concatenate([[0.0], np.cumsum(duration + pause)[:-1]])
        heading = np.empty(K)
        prev = 0.0
        for k in range(K):  # a vertical segment keeps the heading before it
            h = math.hypot(delta[k, 0], delta[k, 1])
            prev = math.atan2(delta[k, 1], delta[k, 0]) if h > 1e-9 else prev
            heading[k] = prev
        if math.hypot(delta[0, 0], delta[0, 1]) <= 1e-9:  # first segment vertical: next horizontal heading
            nz = [k for k in range(K) if math.hypot(delta[k, 0], delta[k, 1]) > 1e-9]
            if nz:
                heading[: nz[0]] = heading[nz[0]]
        return {
            "starts_list": (seg_start.tolist(), heading.tolist()),
            "p0": p0,
            "p1": p1,
            "dir": direction,
            "speed": speed,
            "duration": duration,
            "seg_start": seg_start,
            "heading": heading,
            "cycle_s": float(np.sum(duration + pause)),
        }

    @property
    def cycle_s(self) -> float:
        """Seconds of one loop (or of the whole one-way path, pauses included)."""
        return float(self._timeline["cycle_s"])

    @property
    def length_m(self) -> float:
        """Length of one loop (or of the one-way path), metres."""
        tl = self._timeline
        return float(np.sum(tl["duration"] * tl["speed"]))


@dataclass(frozen=True)
class CircleMotion:
    """Constant speed on a horizontal circle (module docstring).

    center_m : (x, y, z) metres, world ENU; the actor frame's origin stays at ``z`` of the centre
    radius_m : m > 0
    speed_mps : m/s > 0, along the circle
    phase_rad : angle of the start position about the centre, from +x, counter-clockwise
    clockwise : direction seen from above
    start_s : s, world-clock time the actor starts walking
    """

    center_m: tuple[float, float, float]
    radius_m: float
    speed_mps: float
    phase_rad: float = 0.0
    clockwise: bool = False
    start_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_m", _finite_vec3(self.center_m, "center_m"))
        _positive(self.radius_m, "radius_m")
        _positive(self.speed_mps, "speed_mps")
        if not (isinstance(self.phase_rad, (int, float)) and math.isfinite(self.phase_rad)):
            raise MotionFormatError("phase_rad", f"must be a finite number, got {self.phase_rad!r}")
        if not (isinstance(self.start_s, (int, float)) and math.isfinite(self.start_s)):
            raise MotionFormatError("start_s", f"must be a finite number, got {self.start_s!r}")

    @property
    def cycle_s(self) -> float:
        """Seconds of one lap."""
        return 2.0 * math.pi * self.radius_m / self.speed_mps


Motion = Union[PathMotion, CircleMotion]


@dataclass(frozen=True, eq=False)
class ActorPose:
    """An actor's pose at one instant.

    position_m : float (3,), origin of the actor frame, metres, world ENU
    yaw_rad : heading of the actor frame's x axis about +z, radians in (-pi, pi]
    velocity_mps : float (3,), velocity of the origin, m/s, world ENU (zero when standing)
    moving : False while paused, before the start and after a one-way path ends
    """

    position_m: np.ndarray
    yaw_rad: float
    velocity_mps: np.ndarray
    moving: bool

    @property
    def T_world_actor(self) -> np.ndarray:
        """(4, 4) actor frame -> world ENU."""
        return T_world_actor(self.position_m, self.yaw_rad)


def T_world_actor(position_m, yaw_rad: float) -> np.ndarray:
    """(4, 4) transform of an upright actor frame at ``position_m`` (3,) with heading ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = np.asarray(position_m, dtype=float)
    return T


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi] (same convention as ``planning.frames.wrap_angle``)."""
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w <= -np.pi, w + 2.0 * np.pi, w)


def _path_poses(m: PathMotion, t: np.ndarray):
    tl = m._timeline
    tau = t - m.start_s
    before = tau < 0
    cycle = tl["cycle_s"]
    if m.loop:
        tau = np.mod(np.maximum(tau, 0.0), cycle)
        ended = np.zeros_like(before)
    else:
        ended = tau >= cycle
        tau = np.clip(tau, 0.0, cycle)
    seg_start = tl["seg_start"]
    k = np.clip(np.searchsorted(seg_start, tau, side="right") - 1, 0, len(seg_start) - 1)
    local = tau - seg_start[k]
    dur = tl["duration"][k]
    walking = (local < dur) & ~before & ~ended
    s = np.minimum(local, dur) * tl["speed"][k]  # distance along the segment
    pos = tl["p0"][k] + tl["dir"][k] * s[:, None]
    at_end = ~walking & ~before  # a pause or the end of a one-way path: exactly at the corner
    pos[at_end] = tl["p1"][k[at_end]]
    pos[before] = tl["p0"][0]
    yaw = tl["heading"][k]
    yaw[before] = tl["heading"][0]
    vel = np.where(walking[:, None], tl["dir"][k] * tl["speed"][k][:, None], 0.0)
    return pos, _wrap(yaw), vel, walking


def _circle_poses(m: CircleMotion, t: np.ndarray):
    sign = -1.0 if m.clockwise else 1.0
    omega = m.speed_mps / m.radius_m
    tau = np.maximum(t - m.start_s, 0.0)
    theta = m.phase_rad + sign * omega * tau
    c = np.asarray(m.center_m, dtype=float)
    pos = np.empty((len(t), 3))
    pos[:, 0] = c[0] + m.radius_m * np.cos(theta)
    pos[:, 1] = c[1] + m.radius_m * np.sin(theta)
    pos[:, 2] = c[2]
    walking = t >= m.start_s
    tangent = np.stack([-np.sin(theta), np.cos(theta), np.zeros_like(theta)], axis=1) * sign
    vel = np.where(walking[:, None], tangent * m.speed_mps, 0.0)
    yaw = theta + sign * 0.5 * np.pi
    return pos, _wrap(yaw), vel, walking


def poses_at(motion: Motion, t_s) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Poses at many times (vectorised).

    Parameters
    ----------
    motion : PathMotion or CircleMotion
    t_s : array (N,) or scalar, seconds on the world clock

    Returns
    -------
    position_m (N, 3) world ENU, yaw_rad (N,), velocity_mps (N, 3), moving bool (N,)
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=float)).reshape(-1)
    if not np.all(np.isfinite(t)):
        raise ValueError(f"t_s must be finite, got {t_s!r}")
    if isinstance(motion, PathMotion):
        return _path_poses(motion, t)
    if isinstance(motion, CircleMotion):
        return _circle_poses(motion, t)
    raise TypeError(f"expected a PathMotion or CircleMotion, got {type(motion).__name__}")


def positions_at(motion: Motion, t_s) -> np.ndarray:
    """Positions (N, 3), metres, world ENU, of the actor frame's origin at times ``t_s`` (N,)."""
    return poses_at(motion, t_s)[0]


def _wrap1(a: float) -> float:
    w = (a + math.pi) % (2.0 * math.pi) - math.pi
    return w + 2.0 * math.pi if w <= -math.pi else w


def _path_pose1(m: PathMotion, t: float) -> ActorPose:
    """Scalar :func:`_path_poses` (the renderer asks once per actor per frame: no array setup)."""
    tl = m._timeline
    starts = tl["starts_list"]
    tau = t - m.start_s
    if tau < 0:
        return ActorPose(tl["p0"][0].copy(), _wrap1(starts[1][0]), np.zeros(3), False)
    cycle = tl["cycle_s"]
    ended = False
    if m.loop:
        tau = tau % cycle
    elif tau >= cycle:
        ended, tau = True, cycle
    k = max(0, min(bisect_right(starts[0], tau) - 1, len(starts[0]) - 1))
    local = tau - starts[0][k]
    dur = float(tl["duration"][k])
    yaw = _wrap1(starts[1][k])
    if ended or local >= dur:
        return ActorPose(tl["p1"][k].copy(), yaw, np.zeros(3), False)
    d = tl["dir"][k]
    v = float(tl["speed"][k])
    return ActorPose(tl["p0"][k] + d * (local * v), yaw, d * v, True)


def pose_at(motion: Motion, t_s: float) -> ActorPose:
    """The actor's :class:`ActorPose` at ``t_s`` seconds on the world clock (the same values as
    :func:`poses_at`, computed without array setup)."""
    t = float(t_s)
    if not math.isfinite(t):
        raise ValueError(f"t_s must be finite, got {t_s!r}")
    if isinstance(motion, PathMotion):
        return _path_pose1(motion, t)
    if isinstance(motion, CircleMotion):
        sign = -1.0 if motion.clockwise else 1.0
        walking = t >= motion.start_s
        theta = motion.phase_rad + sign * (motion.speed_mps / motion.radius_m) * max(t - motion.start_s, 0.0)
        c, s_ = math.cos(theta), math.sin(theta)
        cx, cy, cz = motion.center_m
        pos = np.array([cx + motion.radius_m * c, cy + motion.radius_m * s_, cz])
        vel = np.array([-s_ * sign * motion.speed_mps, c * sign * motion.speed_mps, 0.0]) if walking else np.zeros(3)
        return ActorPose(pos, _wrap1(theta + sign * 0.5 * math.pi), vel, walking)
    raise TypeError(f"expected a PathMotion or CircleMotion, got {type(motion).__name__}")


# -- the scene-format table --------------------------------------------------------------------

_PATH_KEYS = ("type", "loop", "start_s", "waypoints")
_WAYPOINT_KEYS = ("position_m", "speed_mps", "pause_s")
_CIRCLE_KEYS = ("type", "center_m", "radius_m", "speed_mps", "phase_deg", "clockwise", "start_s")


def _check_keys(table: dict, allowed: tuple[str, ...], prefix: str, where: str) -> None:
    for k in table:
        if k not in allowed:
            raise MotionFormatError(f"{prefix}{k}", f"unknown field (allowed: {', '.join(allowed)})", where)


def _number(table: dict, key: str, default: Any, prefix: str, where: str) -> float:
    if key not in table:
        if default is ...:
            raise MotionFormatError(f"{prefix}{key}", "missing required field", where)
        return default
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise MotionFormatError(f"{prefix}{key}", f"expected a finite number, got {type(v).__name__} {v!r}", where)
    return float(v)


def _flag(table: dict, key: str, default: bool, where: str) -> bool:
    v = table.get(key, default)
    if not isinstance(v, bool):
        raise MotionFormatError(key, f"expected true or false, got {type(v).__name__} {v!r}", where)
    return v


def _vec3(table: dict, key: str, prefix: str, where: str) -> tuple[float, float, float]:
    if key not in table:
        raise MotionFormatError(f"{prefix}{key}", "missing required field", where)
    v = table[key]
    if (
        not isinstance(v, (list, tuple))
        or len(v) != 3
        or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in v)
    ):
        raise MotionFormatError(f"{prefix}{key}", f"expected a list of 3 finite numbers, got {v!r}", where)
    return (float(v[0]), float(v[1]), float(v[2]))


def parse_motion(table: Any, where: str = "motion") -> Motion:
    """A motion from its scene-format table (module docstring, ``docs/scene_format.md``).

    Parameters
    ----------
    table : dict, the parsed TOML table
    where : prefix of error messages (e.g. ``"plaza.toml: object 'person in red': motion"``)

    Raises
    ------
    MotionFormatError naming the field (``.field``) and the problem (``.detail``).
    """
    if not isinstance(table, dict):
        raise MotionFormatError(None, f"expected a table, got {type(table).__name__} {table!r}", where)
    kind = table.get("type")
    if kind not in MOTION_TYPES:
        detail = "missing required field" if kind is None else f"unknown motion type {kind!r}"
        raise MotionFormatError("type", f"{detail} (known: {', '.join(MOTION_TYPES)})", where)
    try:
        if kind == "path":
            _check_keys(table, _PATH_KEYS, "", where)
            raw = table.get("waypoints")
            if not isinstance(raw, list):
                raise MotionFormatError("waypoints", f"expected a list of waypoint tables, got {raw!r}", where)
            wps = []
            for i, w in enumerate(raw):
                pre = f"waypoints[{i}]."
                if not isinstance(w, dict):
                    raise MotionFormatError(f"waypoints[{i}]", f"expected a table, got {type(w).__name__} {w!r}", where)
                _check_keys(w, _WAYPOINT_KEYS, pre, where)
                pos = _vec3(w, "position_m", pre, where)
                speed = _number(w, "speed_mps", ..., pre, where)
                if speed <= 0:
                    raise MotionFormatError(f"{pre}speed_mps", f"must be > 0, got {speed}", where)
                pause = _number(w, "pause_s", 0.0, pre, where)
                if pause < 0:
                    raise MotionFormatError(f"{pre}pause_s", f"must be >= 0, got {pause}", where)
                wps.append(Waypoint(pos, speed, pause))
            return PathMotion(tuple(wps), _flag(table, "loop", True, where), _number(table, "start_s", 0.0, "", where))
        _check_keys(table, _CIRCLE_KEYS, "", where)
        center = _vec3(table, "center_m", "", where)
        radius = _number(table, "radius_m", ..., "", where)
        if radius <= 0:
            raise MotionFormatError("radius_m", f"must be > 0, got {radius}", where)
        speed = _number(table, "speed_mps", ..., "", where)
        if speed <= 0:
            raise MotionFormatError("speed_mps", f"must be > 0, got {speed}", where)
        return CircleMotion(
            center,
            radius,
            speed,
            math.radians(_number(table, "phase_deg", 0.0, "", where)),
            _flag(table, "clockwise", False, where),
            _number(table, "start_s", 0.0, "", where),
        )
    except MotionFormatError as exc:
        if str(exc).startswith(where):
            raise
        raise MotionFormatError(exc.field, exc.detail, where) from None
