"""Every parameter of the local ESDF map, in one frozen dataclass.

Defaults follow the issue and the paper where they say something (0.1 m voxels, D_max = 7 m);
the rest are our documented choices (log-odds after OctoMap / Fast-Planner). The defaults are
the *safe* ones for a real depth camera, used by every path that flies or replays (the pilot,
``onfly fly``, ``onfly replay``, the benchmark): unknown space is an obstacle, a pixel without a
reading clears only a bounded, neighbour-limited stretch of its ray, the vehicle's own body
sphere is free, and the window covers ``max_range_m`` (the verifier's D_max) plus a margin.
``docs/esdf_unknown_space.md`` explains the policy, its sources and its measured cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

__all__ = ["EsdfConfig", "EsdfConfigError", "UNKNOWN_POLICIES"]

#: Valid values of :attr:`EsdfConfig.unknown_policy`.
UNKNOWN_POLICIES = ("free", "occupied")


class EsdfConfigError(ValueError):
    """An :class:`EsdfConfig` field out of range; the message names the field."""


@dataclass(frozen=True)
class EsdfConfig:
    """Parameters of :class:`planning.esdf.EsdfMap`.

    Grid
    ----
    voxel_m : edge of a cubic voxel, metres. Voxels sit on the global lattice
        ``floor(p_world / voxel_m)``, so the rolling window moves by whole voxels.
    size_m : (x, y, z) extent of the rolling window in world axes, metres; each is rounded to a
        whole number of voxels (at least 2). Default 16 x 16 x 5 m around the vehicle: the
        horizontal half-width (8 m) covers the verifier's D_max (``max_range_m``, 7 m) plus 1 m,
        so a goal check at 7 m reads the field, not the value clamped at the window's face
        (the old 10 x 10 m window ended at 5 m). Vertically +-2.5 m.

    Sensor model
    ------------
    max_range_m : D_max of the paper (7 m). Readings beyond it mark no obstacle; they only clear
        free space up to ``max_range_m`` along their ray (an inf reading is no reading).
    min_range_m : readings closer than this are dropped as no reading (sensor dead zone,
        propellers in view).
    stride_px : back-project every ``stride_px``-th row and column for obstacle hits. Free-space
        clearing always looks up the full-resolution image. At 640 x 480 with fx ~ 320-585 and
        stride 2, neighbouring samples are at most 5 cm apart at 7 m, below one voxel.
    clear_margin_m : a voxel is passed through (a miss) only when its centre's z-depth is at
        least this much shorter than the reading of the pixel it projects to; keeps the voxel
        that holds the surface (its centre may sit half a voxel diagonal in front) and absorbs
        depth noise.
    surface_thickness_m : besides the voxel holding each measured point, the voxels up to this
        far behind it along the ray are also hit, so thin observed shells get an inside
        (negative distance) under ``unknown_policy="free"``. Off (0) by default: at convex edges
        seen at grazing angles the band pokes out of the far face by up to this much, which
        the benchmark measured as errors above one voxel (0.14 m with 0.2 m). With unknown as
        occupied the unseen interior is solid anyway. (Fast-Planner has no band either: there,
        too, only thick occupied regions read negative.)

    Occupancy (log-odds, one update per voxel per frame; a hit wins over a miss)
    ---------------------------------------------------------------------------
    hit_logodds : added on a hit (0.85 = p 0.70).
    miss_logodds : added on a miss, negative (-0.4 = p 0.40).
    min_logodds, max_logodds : clamps; with the defaults a fully confident obstacle is cleared
        after 6 frames that see through it (float32 arithmetic: 2.0 - 5 * 0.4 is still 6e-8 > 0),
        and one frame of hits makes a voxel occupied.
    occupied_logodds : a voxel is occupied when its log-odds exceed this (0 = p 0.5).

    Distance field
    --------------
    max_distance_m : clamp of the Euclidean distance transform. Distances beyond it are
        reported as exactly ``max_distance_m`` (gradient 0 there), and the incremental update
        only recomputes the changed box grown by this distance (Fast-Planner's idea), so it is
        the main cost knob. Within the clamp the field is the exact voxel-centre EDT. It must
        exceed the largest clearance the planner asks of the field: ``d_safe_m`` plus its
        tracking margin (up to ``tracking_margin_max_m``) plus the goal's margin,
        0.45 + 1.0 + 0.05 m with the defaults (``PlannerConfig.field_reach_m``). Default 1.6 m;
        it was 1.0 m, and under gusts (a margin above 0.5 m) no point of the map could show the
        clearance the planner asked for: every plan fell back and the vehicle drifted (the
        realistic world, ``docs/robustness.md``).
    max_inside_distance_m : clamp of the depth inside obstacles (negative side). A body centre
        half a metre inside an obstacle has already crashed, so a short clamp is enough to give
        a gradient out of thin obstacles and costs less.
    unknown_policy : what never-observed space means for the field: ``"occupied"`` (default,
        conservative: unknown voxels and the space outside the grid are obstacles, so the
        planner flies only where rays have passed; every unknown voxel of the frustum is
        projected to mark observed free space; the shell of ``clear_margin_m`` in front of a
        surface that no ray saw past stays unknown, so obstacles read up to that much closer)
        or ``"free"`` (Fast-Planner's optimistic map: only observed obstacles count; cheapest,
        but a hole in the depth image, or space the camera never saw, is open space; kept for
        comparisons and ideal-world studies).

    Pixels without a reading (sky, glass, dark or shiny surfaces, beyond range, nearer than
    ``min_range_m``)
    ------------------------------------------------------------------------------------
    no_reading_clear_m : a pixel without a reading clears (passes through) voxels along its
        ray up to z-depth ``min(no_reading_clear_m, r_nb) - clear_margin_m``, where ``r_nb`` is
        the nearest reading met scanning the pixel's row and column outward in the four image
        directions (each clipped to ``max_range_m``); a pixel whose scans meet no reading, and
        every pixel of a frame with no reading at all, clears nothing. It never
        clears a voxel that is occupied (no reading is no evidence against an observed
        obstacle). Default 4.5 m, Fast-Planner's and EGO-Planner's ``max_ray_length`` (their
        depth fusion turns a 0 pixel into a free ray of that length). The neighbour bound keeps
        a hole in a wall (glass, a dark patch) from clearing past the wall around it, since the
        wall's readings lie on the hole's row and column; the length bound lets open sky above
        the horizon clear the space the vehicle flies through. 0 turns it off (no-reading
        pixels clear nothing; outdoors the vehicle then sees almost nothing free at its height).
    no_reading_needs_below : True (default): a pixel without a reading clears nothing unless
        its column holds a reading below it. A hole that reaches the image's bottom edge runs
        on out of view, where a level camera sees what is nearest; its readings above are the
        surface *behind* it (the floor past a dark conveyor belt the vehicle flies beside, an
        object nearer than ``min_range_m``), so they bound nothing: the no-reading rule marked
        such an object's voxels free, and OnFly flew into the belt of ``factory_hall-l02``
        under the realistic profile. Sky and far ground lie above readable ground and keep
        clearing. False = the four scans alone
    body_clear_radius_m : every :meth:`planning.esdf.EsdfMap.integrate` marks the *unknown*
        voxels within this radius of the vehicle free (the vehicle is there; voxblox's
        ``clear_sphere_radius``, default 1.5 m, does the same for planning). Never overrides an
        observed voxel. Default 1.2 m: a level camera with a 60 deg vertical field of view sees
        nothing below the plane 30 deg under its axis, so the vehicle's first metre of flight
        has unknown space (an obstacle) within ``r * sin(30 deg)`` below it; with 1.2 m the
        clearance along a straight start stays above ~0.6 m, more than the planner's
        ``d_safe_m`` (0.45 m), while at the 1.5 m flight height the sphere stays clear of the
        ground. 0 turns it off. A caller that flies a planner with a tracking margin grows the
        radius by that margin each frame (``EsdfMap.integrate(body_margin_m=...)``), so the
        sphere keeps exceeding the clearance the planner asks for.
    body_clear_above_m : the sphere clears no voxel whose centre lies more than this above the
        vehicle, metres (None = the whole sphere). A level camera with a 60 deg vertical field
        of view never sees the space straight above it, and a room's ceiling is often nearer
        than the sphere's radius (2.6 m over a vehicle at 1.5 m: 1.1 m, inside 1.2 m); the
        whole sphere marked that ceiling free, and it rose with the vehicle, so a goal raised
        into it (the goal check's lift) was raised again every step: the oracle climbed at
        0.3 m/s into the apartment's ceiling (``apartment-o09``, ``apartment-l05`` in the hard
        set). Default 0.5 m: above ``d_safe_m`` (0.45 m) by a voxel, so a vehicle hovering at
        the height it reached keeps its clearance, and under the 0.25 m lift step plus the goal
        clearance (0.5 m), so a goal is never lifted into the sphere. The camera still clears
        the space ahead and above in view (30 deg up), so a vehicle climbs while it flies on.
        Like the radius it grows by ``body_margin_m`` (the planner's tracking margin, which the
        MPC adds to ``d_safe_m``: fixed, it failed plans of a hovering vehicle in gusts), and
        so does the clearance the goal check's lift asks, so the lift still finds no room in it
    body_clear_in_view : False (default): the sphere leaves alone the voxels the frame's camera
        looks at (their centre projects into the image), so it only fills in what the camera
        cannot see from where it is: below, behind and beside its view. A voxel in view that
        the frame left unknown lies behind a surface or on a pixel without a reading, and the
        vehicle being near it is no evidence that it is free: with the sphere clearing in view,
        a vehicle approaching a dark machine or a glass pane that gives no depth erased the
        object from its map 1.2 m ahead of itself and flew into it (three realistic-world
        episodes of the robustness run, ``docs/esdf_unknown_space.md``). True is the old
        sphere, kept for comparisons.
    body_clear_recent_views : with ``body_clear_in_view`` False, the sphere also leaves alone
        the voxels that projected into one of this many earlier frames' images within
        ``no_reading_clear_m`` of their camera: the camera looked at them from where an unread
        pixel would have cleared them, and they stayed unknown (a dark or glass surface, or the
        inside of an object). Without it a dark object the vehicle had just looked at was
        erased once a turn or a gust put it beside or below the view (``factory_hall-l02``:
        the dark conveyor belt, after a turn toward a goal 50 deg off; ``factory_hall-o05``: the
        forklift's dark mast). Beyond that range, unknown is what an unread pixel leaves anyway.
        Default 20 frames (10 s at the benchmark's 2 Hz). 0 = the current frame only

    Speed
    -----
    reach_cull : before projecting voxels to clear them, drop every 8^3-voxel block none of whose
        voxel centres can be passed through: its nearest centre (z-depth) is at or beyond the
        largest clearing reach (:func:`planning.esdf_occupancy.free_reach`) over the image
        rectangle its centres project into (a max over 8 x 8-pixel tiles, looked up in a sparse
        table). A cull only, so the map is the same with it off; it removes the unknown space
        behind surfaces and beyond the no-reading bound, which the ``"occupied"`` policy would
        otherwise re-project every frame. False = project every candidate of the frustum
        (kept for comparisons: ``experiments/bench_esdf.py``).
    """

    voxel_m: float = 0.1
    size_m: tuple[float, float, float] = (16.0, 16.0, 5.0)
    max_range_m: float = 7.0
    min_range_m: float = 0.05
    stride_px: int = 2
    clear_margin_m: float = 0.15
    surface_thickness_m: float = 0.0
    hit_logodds: float = 0.85
    miss_logodds: float = -0.4
    min_logodds: float = -2.0
    max_logodds: float = 2.0
    occupied_logodds: float = 0.0
    max_distance_m: float = 1.6
    max_inside_distance_m: float = 0.5
    unknown_policy: Literal["free", "occupied"] = "occupied"
    no_reading_clear_m: float = 4.5
    no_reading_needs_below: bool = True
    body_clear_radius_m: float = 1.2
    body_clear_above_m: float | None = 0.6
    body_clear_in_view: bool = False
    body_clear_recent_views: int = 20
    reach_cull: bool = True

    def __post_init__(self) -> None:
        def positive(name: str) -> None:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise EsdfConfigError(f"{name} must be a positive finite number, got {value!r}")

        for name in ("voxel_m", "max_range_m", "max_distance_m", "max_inside_distance_m", "hit_logodds"):
            positive(name)
        for name in ("min_range_m", "clear_margin_m", "surface_thickness_m", "no_reading_clear_m", "body_clear_radius_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise EsdfConfigError(f"{name} must be a finite number >= 0, got {value!r}")
        if self.body_clear_above_m is not None:
            above = self.body_clear_above_m
            if not (isinstance(above, (int, float)) and not isinstance(above, bool) and math.isfinite(above) and above >= 0):
                raise EsdfConfigError(f"body_clear_above_m must be a finite number >= 0 or None, got {above!r}")
        if self.min_range_m >= self.max_range_m:
            raise EsdfConfigError(
                f"min_range_m ({self.min_range_m}) must be smaller than max_range_m ({self.max_range_m})"
            )
        size = tuple(self.size_m)
        if len(size) != 3 or not all(isinstance(s, (int, float)) and math.isfinite(s) for s in size):
            raise EsdfConfigError(f"size_m must be three finite numbers (x, y, z), got {self.size_m!r}")
        if min(size) < 2 * self.voxel_m:
            raise EsdfConfigError(f"size_m must be at least two voxels ({2 * self.voxel_m} m) per axis, got {size}")
        object.__setattr__(self, "size_m", tuple(float(s) for s in size))
        if not (isinstance(self.stride_px, int) and not isinstance(self.stride_px, bool) and self.stride_px >= 1):
            raise EsdfConfigError(f"stride_px must be an integer >= 1, got {self.stride_px!r}")
        if not (math.isfinite(self.miss_logodds) and self.miss_logodds < 0):
            raise EsdfConfigError(f"miss_logodds must be negative, got {self.miss_logodds!r}")
        if not (self.min_logodds < self.occupied_logodds < self.max_logodds):
            raise EsdfConfigError(
                "need min_logodds < occupied_logodds < max_logodds, got "
                f"{self.min_logodds} / {self.occupied_logodds} / {self.max_logodds}"
            )
        if self.hit_logodds <= self.occupied_logodds:
            # A first hit starts from 0 (unknown); it must be able to make a voxel occupied.
            raise EsdfConfigError(
                f"hit_logodds ({self.hit_logodds}) must exceed occupied_logodds ({self.occupied_logodds})"
            )
        if not isinstance(self.body_clear_in_view, bool):
            raise EsdfConfigError(f"body_clear_in_view must be true or false, got {self.body_clear_in_view!r}")
        if not (isinstance(self.body_clear_recent_views, int) and not isinstance(self.body_clear_recent_views, bool)
                and self.body_clear_recent_views >= 0):  # fmt: skip
            raise EsdfConfigError(f"body_clear_recent_views must be an integer >= 0, got {self.body_clear_recent_views!r}")
        if not isinstance(self.no_reading_needs_below, bool):
            raise EsdfConfigError(f"no_reading_needs_below must be true or false, got {self.no_reading_needs_below!r}")
        if not isinstance(self.reach_cull, bool):
            raise EsdfConfigError(f"reach_cull must be true or false, got {self.reach_cull!r}")
        if self.unknown_policy not in UNKNOWN_POLICIES:
            raise EsdfConfigError(f"unknown_policy must be one of {UNKNOWN_POLICIES}, got {self.unknown_policy!r}")
        for name in ("max_distance_m", "max_inside_distance_m"):
            if getattr(self, name) / self.voxel_m > 180:
                raise EsdfConfigError(f"{name} must be at most 180 voxels ({180 * self.voxel_m} m)")

    # -- derived quantities -----------------------------------------------------------------
    @property
    def grid_shape(self) -> tuple[int, int, int]:
        """Voxels per axis ``(nx, ny, nz)``: ``size_m / voxel_m`` rounded, at least 2."""
        return tuple(max(2, int(round(s / self.voxel_m))) for s in self.size_m)

    @property
    def max_distance_voxels(self) -> int:
        """Outside clamp in voxels, rounded up so every distance <= ``max_distance_m`` is exact."""
        return max(1, math.ceil(self.max_distance_m / self.voxel_m - 1e-9))

    @property
    def max_inside_voxels(self) -> int:
        """Inside transform clamp in voxels: inside depth is ``(d_in - 1) * voxel_m``, so one more."""
        return math.ceil(self.max_inside_distance_m / self.voxel_m - 1e-9) + 1
