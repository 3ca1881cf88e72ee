"""Moving obstacles seen in depth: constant-velocity tracks and the space they will sweep.

The ESDF (:mod:`planning.esdf`) is a map of where things *were*: a person walking through
space seen free is in it where the last frame saw them (and, for a few frames, where earlier
frames did), and nothing in it says where they will be. This module gives the planner that prediction from the same depth frames, with
no labels (it works with any perception backend):

1. **Detection**: a depth reading inside a voxel the map has seen free (log-odds at most
   ``MoverConfig.free_logodds_max``) *before* this frame, and at least ``clear_m`` from
   anything the map holds (unknown space included), is something that moved there. The
   clearance keeps depth noise on known surfaces out: a RealSense's readings of a wall at
   grazing incidence scatter into the voxels just in front of it, which earlier, deeper
   readings carved free. Readings at a depth edge (a 4-neighbour more than ``edge_jump`` of the
   depth away: flying pixels, silhouettes) are left out, and so are readings beyond
   ``max_range_m``, where depth noise is large. Within ``young_max_range_m`` the clearance is
   not asked of a *young* obstacle: one whose voxel was seen free and then hit once (log-odds
   between ``EsdfConfig.occupied_logodds`` and ``hit_logodds``), which is how a mover's own
   trace enters the map. At 2 Hz a walker at 0.45 m/s moves 0.23 m between frames, less than
   ``clear_m`` from where the map put it a frame before; without this rule such a walker is
   seen once and never tracked (the tables of record's `duplex-l02`, run 1, flew into one). A
   surface first seen from unknown space enters at ``hit_logodds`` and is never young; beyond
   3 m the D435's noise would make young phantoms of static clutter.
2. **Clusters**: those readings binned on a horizontal grid of ``cell_m`` cells and joined by
   8-connectivity; a cluster of at least ``min_points`` readings that stands at least
   ``min_height_m`` tall is one observation (its centroid, horizontal radius and height
   range). The height test rejects flat phantoms: the floor far ahead, read at a grazing
   angle, lands in voxels an earlier ray carved free just above it, and moves with the camera.
3. **Tracks**: observations are matched to the tracks' predicted positions (nearest first,
   within ``gate_m`` plus what ``speed_max_mps`` allows since the track was last seen); the
   velocity is the displacement over the first two observations, then an alpha-beta filter
   (``alpha``, ``beta``). A track is dropped ``keep_s`` after its last observation, or at once
   when the camera sees through its predicted position.
   **A mover leaves where it was**: once a track's centre is more than its radius plus
   ``left_m`` from where it was first observed, a frame that reads a surface *at* that first
   place (the depth there within ``still_tol_m`` plus the D435's 3-sigma noise of the range,
   ``docs/realism.md``) shows that something is still there, and the track is static for good.
   This is how a surface the camera sweeps past close by looks: a wall 0.9 m to the side of a
   vehicle turning at 0.4 rad/s comes into view 0.36 m further along every second, in voxels
   that rays grazing along it carved free, and the young rule above takes each new stretch
   for something that moved there (a static school corridor made 12 "movers" in 24 episodes).
   A walker's first place is seen empty behind it, or hidden by the walker when it comes
   straight at the camera, and neither makes it static.
4. **Prediction** (:class:`MoverField`): a confirmed track (``confirm_hits`` observations,
   moved beyond its radius plus ``left_m`` from its first place, not static) moving faster
   than ``moving_speed_mps`` occupies a vertical capsule from its predicted
   position now to where it will be ``horizon_s`` later, widened by its radius. The planner
   reads the minimum of the map and the capsules' signed distances, so it keeps its clearance
   from where a walker is going, not only from where the map last saw them. Slower tracks are
   left to the map, which holds things that stand still.

This is ours, not the paper's (the paper's planner avoids the static map only). Frames:
points are world ENU metres, z up. Times are the caller's clock, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage as ndi

from planning.camera import PinholeCamera
from planning.field import DistanceField
from planning.frames import check_transform, invert_transform

__all__ = ["MoverConfig", "MoverConfigError", "MoverTrack", "MoverTracker", "MoverField"]

#: the D435's depth noise at 320 px, sigma = this times z^2 (metres, z in metres; the figure
#: ``young_max_range_m`` uses, docs/realism.md)
_D435_SIGMA_PER_M2 = 0.01


class MoverConfigError(ValueError):
    """A :class:`MoverConfig` value out of range."""


@dataclass(frozen=True)
class MoverConfig:
    """Detection, tracking and prediction of moving obstacles (module docstring).

    Attributes
    ----------
    enabled : False = the planner sees the map alone (the behaviour before moving obstacles)
    stride_px : detection reads every ``stride_px``-th row and column of the depth image
    max_range_m : readings farther than this are not used (D435 noise grows with range^2)
    edge_jump : a reading whose 4-neighbour differs by more than this fraction of its depth is
        at an edge (a flying pixel or a silhouette) and is not used
    free_logodds_max : a reading counts as new only in a voxel whose log-odds are at most this
        before the frame. The map applies misses to obstacle and unknown voxels only, so a voxel
        seen free reads ``miss_logodds`` (-0.4) and one hit makes it an obstacle again; the
        default -0.3 is "seen free" 
    cell_m : horizontal cell of the clustering grid, metres
    clear_m : a new reading must be at least this far from the map's obstacles and unknown
        space (the map's distance before the frame), metres
    min_points : readings a cluster needs to be an observation
    min_height_m : vertical extent of its readings a cluster needs, metres (people, carts and
        vehicles stand; the floor does not)
    gate_m : association gate around a track's predicted position, metres, plus
        ``speed_max_mps`` times the time since it was last seen (capped at ``keep_s``)
    speed_max_mps : the fastest mover tracked (a running person, about 3 m/s); a velocity
        estimate above it is clipped to it
    alpha, beta : position and velocity gains of the alpha-beta filter
    confirm_hits : observations before a track is predicted
    moving_speed_mps : a confirmed track slower than this is left to the map
    keep_s : a track not observed for this long is dropped, seconds
    horizon_s : the capsule reaches this far ahead of the predicted position, seconds
    radius_min_m, radius_max_m : clamp of a cluster's horizontal radius, metres
    left_m : a track is predicted only once its centre is this far (metres) beyond its radius
        from where it was first observed, and its first place is checked from then on
        (module docstring, "a mover leaves where it was")
    still_tol_m : a reading within this (metres, plus 3 sigma of the D435's range noise) of the
        first place's depth means something is still there: the track is static
    young_max_range_m : within this range of the camera (metres) a reading beside an obstacle
        that entered the map from seen-free space a frame ago is new however close it is (item
        1 of the module docstring): there a D435's depth noise at 320 px (sigma = 1 cm x z^2,
        ``docs/realism.md``) stays under a third of ``clear_m``; 0 = never
    """

    enabled: bool = True
    stride_px: int = 2
    max_range_m: float = 7.0
    edge_jump: float = 0.05
    free_logodds_max: float = -0.3
    clear_m: float = 0.3
    cell_m: float = 0.25
    min_points: int = 12
    min_height_m: float = 0.3
    gate_m: float = 0.6
    speed_max_mps: float = 3.0
    alpha: float = 0.6
    beta: float = 0.3
    confirm_hits: int = 2
    moving_speed_mps: float = 0.3
    keep_s: float = 2.0
    horizon_s: float = 1.5
    young_max_range_m: float = 3.0
    radius_min_m: float = 0.2
    radius_max_m: float = 1.0
    left_m: float = 0.1
    still_tol_m: float = 0.15

    def __post_init__(self) -> None:
        positive = ("max_range_m", "edge_jump", "clear_m", "cell_m", "gate_m", "speed_max_mps", "keep_s", "radius_min_m")
        if not (np.isfinite(self.min_height_m) and self.min_height_m >= 0):
            raise MoverConfigError(f"MoverConfig.min_height_m must be >= 0, got {self.min_height_m}")
        for name in positive:
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise MoverConfigError(f"MoverConfig.{name} must be positive, got {v}")
        for name in ("horizon_s", "moving_speed_mps", "young_max_range_m", "left_m", "still_tol_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise MoverConfigError(f"MoverConfig.{name} must be >= 0, got {v}")
        if not (isinstance(self.stride_px, int) and self.stride_px >= 1):
            raise MoverConfigError(f"MoverConfig.stride_px must be an integer >= 1, got {self.stride_px!r}")
        if not (isinstance(self.min_points, int) and self.min_points >= 1):
            raise MoverConfigError(f"MoverConfig.min_points must be an integer >= 1, got {self.min_points!r}")
        if not (isinstance(self.confirm_hits, int) and self.confirm_hits >= 1):
            raise MoverConfigError(f"MoverConfig.confirm_hits must be an integer >= 1, got {self.confirm_hits!r}")
        if not (np.isfinite(self.free_logodds_max) and self.free_logodds_max < 0):
            raise MoverConfigError(f"MoverConfig.free_logodds_max must be negative, got {self.free_logodds_max}")
        for name in ("alpha", "beta"):
            v = getattr(self, name)
            if not (0 < v <= 1):
                raise MoverConfigError(f"MoverConfig.{name} must be in (0, 1], got {v}")
        if not self.radius_max_m >= self.radius_min_m:
            raise MoverConfigError(
                f"MoverConfig.radius_max_m ({self.radius_max_m}) must be >= radius_min_m ({self.radius_min_m})"
            )


@dataclass(frozen=True)
class MoverTrack:
    """One tracked mover, as the planner reads it.

    position_m : (2,) horizontal centre at ``t_s``, world metres
    velocity_mps : (2,) horizontal velocity, m/s
    radius_m : horizontal radius, metres
    z_range_m : (low, high) height of the readings, world metres; the low end reaches
        ``clear_m`` below the lowest reading (readings that near the floor are not used)
    t_s : time of the last observation, seconds
    hits : observations so far
    track_id : unique per tracker
    """

    track_id: int
    position_m: np.ndarray
    velocity_mps: np.ndarray
    radius_m: float
    z_range_m: tuple[float, float]
    t_s: float
    hits: int

    def predicted(self, t_s: float) -> np.ndarray:
        """Horizontal position (2,) at ``t_s`` under constant velocity."""
        return self.position_m + self.velocity_mps * (t_s - self.t_s)

    @property
    def speed_mps(self) -> float:
        return float(np.hypot(*self.velocity_mps))


@dataclass
class _Observation:
    centre: np.ndarray  # (2,)
    radius: float
    z_lo: float
    z_hi: float


@dataclass
class _Track:
    track_id: int
    p: np.ndarray
    v: np.ndarray
    radius: float
    z_lo: float
    z_hi: float
    t_s: float
    hits: int = 1
    first_p: np.ndarray = field(default_factory=lambda: np.zeros(2))
    first_z: float = 0.0  # mid-height of the first observation, world metres
    static: bool = False  # its first place was seen still occupied: never predicted

    def left_first(self, left_m: float) -> bool:
        """The centre is beyond the track's radius plus ``left_m`` from its first place."""
        return float(np.hypot(*(self.p - self.first_p))) > self.radius + left_m

    def frozen(self) -> MoverTrack:
        return MoverTrack(self.track_id, self.p.copy(), self.v.copy(), self.radius, (self.z_lo, self.z_hi), self.t_s, self.hits)


def _beside_young_obstacle(P: np.ndarray, dist: np.ndarray, grad: np.ndarray, esdf) -> np.ndarray:
    """(n,) bool: the obstacle nearest each point is young (seen free, then hit once).

    P : (n, 3) world points, metres; dist, grad : the map's distance (n,) and gradient (n, 3)
    there. The obstacle is read at the foot of the gradient and half a voxel beyond it, and
    both must be young; unknown space (no log-odds) and a flat field (no gradient) never are.
    """
    cfg = esdf.config
    norm = np.linalg.norm(grad, axis=1)
    unit = np.divide(grad, norm[:, None], out=np.zeros_like(grad), where=norm[:, None] > 1e-9)
    foot = P - np.maximum(dist, 0.0)[:, None] * unit
    young = np.ones(len(P), dtype=bool)
    for q in (foot, foot - 0.5 * cfg.voxel_m * unit):
        lo = esdf.logodds(q)
        with np.errstate(invalid="ignore"):
            young &= (lo > cfg.occupied_logodds) & (lo < cfg.hit_logodds - 1e-6)
    return young & (norm > 1e-9)


class MoverTracker:
    """Tracks of moving obstacles from depth frames and the map (module docstring).

    Call :meth:`observe` with each frame *before* the frame goes into the map, then read
    :meth:`field` (the map with the predicted capsules) for the planner.
    """

    def __init__(self, config: MoverConfig | None = None) -> None:
        self.config = config if config is not None else MoverConfig()
        self._tracks: list[_Track] = []
        self._next_id = 0
        self._rays: dict[tuple[PinholeCamera, int], np.ndarray] = {}
        self.observations = 0  # clusters seen, over the tracker's life
        self.active_frames = 0  # frames after which some track was predicted

    def reset(self) -> None:
        self._tracks = []
        self._next_id = 0
        self.observations = 0
        self.active_frames = 0

    # -- detection ------------------------------------------------------------------------------
    def _new_points(self, depth_m: np.ndarray, camera: PinholeCamera, T_world_cam: np.ndarray, esdf) -> np.ndarray:
        """World points (n, 3) of readings in space the map has seen free, ``clear_m`` from the
        map's obstacles but for young ones near the camera (module docstring, item 1)."""
        cfg = self.config
        s = cfg.stride_px
        d = np.asarray(camera.check_image(depth_m, "depth"), dtype=np.float32)[::s, ::s]
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d) & (d > 0) & (d <= cfg.max_range_m)
        # an edge reading: a 4-neighbour (either with no reading or far off) disagrees
        pad = np.pad(np.where(valid, d, np.float32(np.inf)), 1, mode="edge")
        jump = np.zeros(d.shape, dtype=bool)
        for dr, dc in ((0, 1), (2, 1), (1, 0), (1, 2)):
            nb = pad[dr : dr + d.shape[0], dc : dc + d.shape[1]]
            with np.errstate(invalid="ignore"):
                jump |= ~(np.abs(nb - d) <= cfg.edge_jump * d)
        keep = valid & ~jump
        if not keep.any():
            return np.zeros((0, 3))
        key = (camera, s)
        rays = self._rays.get(key)
        if rays is None:
            rays = self._rays[key] = camera.rays()[::s, ::s]
        P_cam = rays[keep] * d[keep][:, None].astype(float)
        T = check_transform(T_world_cam, "T_world_cam")
        P = P_cam @ T[:3, :3].T + T[:3, 3]
        lo = esdf.logodds(P)
        with np.errstate(invalid="ignore"):
            new = lo <= np.float32(cfg.free_logodds_max)
        if new.any():
            P = P[new]
            dist, grad = esdf.query(P)
            ok = dist >= cfg.clear_m
            rng = np.linalg.norm(P - T[:3, 3], axis=1)
            close = np.flatnonzero(~ok & (rng <= cfg.young_max_range_m))
            if len(close):
                ok[close] = _beside_young_obstacle(P[close], dist[close], grad[close], esdf)
            return P[ok]
        return P[new]

    def _clusters(self, P: np.ndarray) -> list[_Observation]:
        cfg = self.config
        if len(P) < cfg.min_points:
            return []
        cells = np.floor(P[:, :2] / cfg.cell_m).astype(np.int64)
        lo = cells.min(axis=0)
        shape = cells.max(axis=0) - lo + 1
        grid = np.zeros(tuple(shape), dtype=bool)
        ij = cells - lo
        grid[ij[:, 0], ij[:, 1]] = True
        labels, n = ndi.label(grid, structure=np.ones((3, 3), dtype=bool))
        point_label = labels[ij[:, 0], ij[:, 1]]
        out = []
        for k in range(1, n + 1):
            Q = P[point_label == k]
            if len(Q) < cfg.min_points or float(np.ptp(Q[:, 2])) < cfg.min_height_m:
                continue
            c = Q[:, :2].mean(axis=0)
            r = float(np.clip(np.max(np.hypot(*(Q[:, :2] - c).T)), cfg.radius_min_m, cfg.radius_max_m))
            # readings within clear_m of the floor were left out: the mover reaches down that far
            out.append(_Observation(c, r, float(Q[:, 2].min()) - cfg.clear_m, float(Q[:, 2].max())))
        return out

    # -- tracking -------------------------------------------------------------------------------
    def observe(self, t_s: float, depth_m, camera: PinholeCamera, T_world_cam, esdf) -> list[MoverTrack]:
        """Update the tracks with one frame; call it *before* ``esdf.integrate`` of the frame.

        Parameters
        ----------
        t_s : the frame's time, seconds
        depth_m : (H, W) z-depth, metres (0 / NaN / inf = no reading)
        camera : the depth camera's intrinsics
        T_world_cam : (4, 4) optical frame -> world
        esdf : the map before this frame (an ``EsdfMap``: ``logodds`` and ``query``)

        Returns the tracks the planner avoids now (:meth:`active`).
        """
        cfg = self.config
        if not cfg.enabled:
            return []
        obs = self._clusters(self._new_points(depth_m, camera, T_world_cam, esdf))
        self.observations += len(obs)
        self._tracks = [t for t in self._tracks if t_s - t.t_s <= cfg.keep_s]
        pairs = []
        for i, tr in enumerate(self._tracks):
            dt = max(t_s - tr.t_s, 0.0)
            pred = tr.p + tr.v * dt
            gate = cfg.gate_m + cfg.speed_max_mps * min(dt, cfg.keep_s)
            for j, o in enumerate(obs):
                d = float(np.hypot(*(o.centre - pred)))
                if d <= gate + o.radius:
                    pairs.append((d, i, j))
        used_t: set[int] = set()
        used_o: set[int] = set()
        for _, i, j in sorted(pairs):
            if i in used_t or j in used_o:
                continue
            used_t.add(i)
            used_o.add(j)
            self._update(self._tracks[i], obs[j], t_s)
        for j, o in enumerate(obs):
            if j not in used_o:
                self._tracks.append(_Track(self._next_id, o.centre.copy(), np.zeros(2), o.radius, o.z_lo, o.z_hi, t_s, 1,
                                           o.centre.copy(), 0.5 * (o.z_lo + cfg.clear_m + o.z_hi)))
                self._next_id += 1
        self._mark_static(depth_m, camera, T_world_cam)
        unseen = [i for i in range(len(self._tracks)) if i not in used_t and self._tracks[i].t_s < t_s]
        if unseen:
            gone = self._seen_through([self._tracks[i] for i in unseen], t_s, depth_m, camera, T_world_cam)
            drop = {unseen[k] for k in np.flatnonzero(gone)}
            self._tracks = [t for i, t in enumerate(self._tracks) if i not in drop]
        active = self.active(t_s)
        self.active_frames += bool(active)
        return active

    def _update(self, tr: _Track, o: _Observation, t_s: float) -> None:
        cfg = self.config
        dt = t_s - tr.t_s
        if dt <= 0:
            return
        if tr.hits == 1:  # the first velocity: the displacement between two observations
            v = (o.centre - tr.p) / dt
            p = o.centre.copy()
        else:
            pred = tr.p + tr.v * dt
            r = o.centre - pred
            p = pred + cfg.alpha * r
            v = tr.v + cfg.beta * r / dt
        speed = float(np.hypot(*v))
        if speed > cfg.speed_max_mps:
            v = v * (cfg.speed_max_mps / speed)
        tr.p, tr.v, tr.t_s, tr.hits = p, v, t_s, tr.hits + 1
        tr.radius = max(o.radius, 0.5 * (tr.radius + o.radius))
        tr.z_lo, tr.z_hi = min(tr.z_lo, o.z_lo), max(tr.z_hi, o.z_hi)

    def _mark_static(self, depth_m, camera: PinholeCamera, T_world_cam) -> None:
        """Mark static every track that has left its first place by its radius plus ``left_m``
        while this frame reads a surface at that place (module docstring, item 3)."""
        cfg = self.config
        todo = [tr for tr in self._tracks if not tr.static and tr.left_first(cfg.left_m)]
        if not todo:
            return
        P = np.array([[tr.first_p[0], tr.first_p[1], tr.first_z] for tr in todo])
        z, cols, rows, inside = self._in_view(P, camera, T_world_cam)
        depth = np.asarray(depth_m, dtype=np.float32)
        h, w = depth.shape
        for k in np.flatnonzero(inside):
            c, r = cols[k], rows[k]
            patch = depth[max(r - 1, 0) : min(r + 2, h), max(c - 1, 0) : min(c + 2, w)]
            with np.errstate(invalid="ignore"):
                ok = patch[np.isfinite(patch) & (patch > 0)]
            if ok.size == 0:
                continue  # a hole: nothing to tell
            tol = cfg.still_tol_m + 3.0 * _D435_SIGMA_PER_M2 * z[k] ** 2
            if abs(float(np.median(ok)) - z[k]) <= tol:
                todo[k].static = True

    def _in_view(self, P: np.ndarray, camera: PinholeCamera, T_world_cam):
        """World points ``P`` (n, 3) in the camera: their z-depth (n,) metres, pixel column and
        row (n,) ints, and whether each is in the image within ``max_range_m`` (n,) bool."""
        T_cam_world = invert_transform(check_transform(T_world_cam, "T_world_cam"))
        Pc = P @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        z = Pc[:, 2]
        uv, _ = camera.project(Pc)
        inside = camera.in_image(uv) & (z > 0) & (z <= self.config.max_range_m)
        px = np.nan_to_num(uv, nan=-1.0).astype(int)  # NaN behind the camera, never inside
        return z, px[:, 0], px[:, 1], inside

    def _seen_through(self, tracks: list[_Track], t_s: float, depth_m, camera: PinholeCamera, T_world_cam) -> np.ndarray:
        """True per track whose predicted centre is in the image with a reading beyond it."""
        out = np.zeros(len(tracks), dtype=bool)
        if not tracks:
            return out
        P = np.array([[*(tr.p + tr.v * (t_s - tr.t_s)), 0.5 * (tr.z_lo + tr.z_hi)] for tr in tracks])
        z, cols, rows, inside = self._in_view(P, camera, T_world_cam)
        depth = np.asarray(depth_m, dtype=np.float32)
        for k in np.flatnonzero(inside):
            reading = float(depth[min(rows[k], depth.shape[0] - 1), min(cols[k], depth.shape[1] - 1)])
            out[k] = np.isfinite(reading) and reading > z[k] + tracks[k].radius + 0.3
        return out

    def active(self, t_s: float) -> list[MoverTrack]:
        """Confirmed tracks that have left their first place and are not static, moving faster
        than ``moving_speed_mps``, seen within ``keep_s``."""
        cfg = self.config
        return [
            t.frozen()
            for t in self._tracks
            if t.hits >= cfg.confirm_hits
            and not t.static
            and t.left_first(cfg.left_m)
            and float(np.hypot(*t.v)) >= cfg.moving_speed_mps
            and t_s - t.t_s <= cfg.keep_s
        ]

    def summary(self) -> dict[str, int]:
        """Counts over the tracker's life: clusters observed, tracks started, frames after
        which some track was predicted."""
        return {"clusters": int(self.observations), "tracks": int(self._next_id), "active_frames": int(self.active_frames)}

    @property
    def tracks(self) -> list[MoverTrack]:
        """Every current track (confirmed or not, moving or not)."""
        return [t.frozen() for t in self._tracks]

    def field(self, base: DistanceField, t_s: float) -> DistanceField:
        """``base`` with the active tracks' capsules (:class:`MoverField`), or ``base`` itself
        when no track is active."""
        tracks = self.active(t_s) if self.config.enabled else []
        if not tracks:
            return base
        return MoverField(base, tracks, t_s, self.config.horizon_s)


class MoverField:
    """A distance field (:class:`planning.field.DistanceField`): the minimum of ``base`` and the
    signed distance to each track's capsule.

    A track's capsule is the horizontal segment from its position predicted at ``t_s`` to the
    one ``horizon_s`` later, widened by its radius, over its height range. Signed distance to
    it: ``hypot(d_h, d_z) - radius`` with ``d_h`` the horizontal distance to the segment and
    ``d_z`` the vertical distance to the height range (0 inside it); the gradient is the unit
    vector from the nearest point of the capsule's core (exact where ``d_h`` or ``d_z`` > 0).
    Other attributes are read from ``base``.
    """

    def __init__(self, base: DistanceField, tracks: list[MoverTrack], t_s: float, horizon_s: float) -> None:
        self.base = base
        self.tracks = list(tracks)
        self.t_s = float(t_s)
        self.horizon_s = float(horizon_s)
        a = np.array([t.predicted(t_s) for t in tracks], dtype=float).reshape(-1, 2)
        self._a = a
        self._ab = np.array([t.velocity_mps * horizon_s for t in tracks], dtype=float).reshape(-1, 2)
        self._r = np.array([t.radius_m for t in tracks], dtype=float)
        self._z = np.array([t.z_range_m for t in tracks], dtype=float).reshape(-1, 2)

    def capsule_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance (n,), gradient (n, 3)) to the nearest capsule; +inf / 0 without tracks."""
        P = np.asarray(points, dtype=float)
        n = len(P)
        best = np.full(n, np.inf)
        grad = np.zeros((n, 3))
        for a, ab, r, (z0, z1) in zip(self._a, self._ab, self._r, self._z):
            L2 = float(ab @ ab)
            w = P[:, :2] - a
            s = np.clip(w @ ab / L2, 0.0, 1.0) if L2 > 0 else np.zeros(n)
            e = np.empty((n, 3))
            e[:, :2] = w - s[:, None] * ab
            e[:, 2] = np.where(P[:, 2] > z1, P[:, 2] - z1, np.where(P[:, 2] < z0, P[:, 2] - z0, 0.0))
            norm = np.sqrt(np.einsum("ij,ij->i", e, e))
            d = norm - r
            closer = d < best
            if closer.any():
                best[closer] = d[closer]
                g = np.zeros((int(closer.sum()), 3))
                nz = norm[closer] > 1e-9
                g[nz] = e[closer][nz] / norm[closer][nz, None]
                # on the core itself: away from the segment, sideways to its direction
                side = np.array([-ab[1], ab[0], 0.0]) if L2 > 0 else np.array([1.0, 0.0, 0.0])
                g[~nz] = side / np.linalg.norm(side)
                grad[closer] = g
        return best, grad

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d0, g0 = self.base.query(points)
        d1, g1 = self.capsule_distance(points)
        nearer = d1 < d0
        if not nearer.any():
            return d0, g0
        d = np.where(nearer, d1, d0)
        g = np.where(nearer[:, None], g1, g0)
        return d, g

    def __getattr__(self, name: str):
        return getattr(self.base, name)
