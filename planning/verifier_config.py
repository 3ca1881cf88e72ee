"""Configuration of the semantic-geometric verifier (paper Sec. "Semantic-Geometric Verified
Local Planning"); the algorithm lives in :mod:`planning.verifier`.

Defaults are the paper's where it states them (tau 0.5, r 0.2 m, D_max 7 m); every other
default is our documented choice, argued next to its field below.

Obstacle rule
-------------
A depth pixel ``j`` is an *obstacle* when it has a valid reading (finite, > 0) closer than the
threshold

    T = max(obstacle_depth_m, d_ref - foreground_margin_m),

where ``d_ref = min(depth(p'), d_max_m)`` is the reference depth of the *refined* pixel ``p'``
(the rule is evaluated where the goal is finally placed: a candidate found under the target's
threshold is re-checked under its own before it is returned), except the pixels of the
target's own surface (below). So two kinds of surfaces are obstacles:

* everything in the **near field** (closer than ``obstacle_depth_m``, default 2 m): at
  0.6 m/s the vehicle covers about 1.8 m during one monitoring period (2 s) plus one VLM call,
  so a goal placed on a surface that close would be reached before anything could stop it;
  a target pixel that falls on such a surface is moved off it (or rejected) -- unless that
  surface is the target itself;
* everything standing **in front of the target** by more than ``foreground_margin_m``
  (default 1 m): occluders and silhouettes the straight flight path toward the target could
  graze. Surfaces within the margin of the target depth are the target itself (a facade seen
  at an angle, the ground around an object's base) and are not obstacles: the paper places the
  goal *at* the target depth ``d'``, and keeping the last metre to the target free of
  obstacles is the job of the planner's ESDF standoff, not of this image-space check. The
  margin of 1 m keeps the ground in front of a ground-level target at 5 m depth seen from 1.5 m
  height free of the target's own ray (the ray clears the ground 1 m in front by 0.3 m > r).

**The target's surface** is the set of pixels depth-continuous with the target pixel (4-connected
neighbours whose depths differ by at most ``surface_jump_ratio`` of the smaller one) within the
band ``[d - foreground_margin_m, d + foreground_margin_m]``; a depth edge (a jump larger than the
ratio) bounds it. Its pixels are never near-field obstacles to a goal on it: a target on a pole 1.5 m
away keeps its goal on the pole's ray instead of being "refined" onto the box behind it. Such a
goal (on a target whose surface reaches into the near field) does not sit on the surface: like a
far target, its range is cut to the clear part of the ray, r in front of the first reading, so a
pixel that noise put on a nearer object still gives a goal r clear of everything the camera saw. The band keeps a contact line with the ground from
joining objects at other depths. Depth-continuous objects within the margin of each other are
one surface for this rule, as they already are for the foreground rule.

Setting ``foreground_margin_m = inf`` gives a pure near-field rule, ``obstacle_depth_m = 0`` a
pure foreground rule.

Pixels without a reading are never open space
---------------------------------------------
A target pixel with no reading (0, NaN, inf: glass, a dark or shiny surface, anything nearer than
the camera's minimum range) is kept, as the paper keeps far targets (``p' = p``), but is assumed
to lie on the surface that bounds the hole: its depth is taken as the smallest reading on the
border of the connected no-reading region around it inside the ROI. The goal stays on the clear
part of the ray in front of that surface (see "Far and unread targets"), so a hole in a wall never
puts a goal behind the wall. Without any reading on that border inside the ROI nothing is known
about the ray: the candidate is rejected (``NO_DEPTH_AT_TARGET``). ``reject_no_reading = True``
rejects every unread target.

Far and unread targets (refinement skipped)
-------------------------------------------
The paper keeps ``p' = p`` beyond D_max. Its range ``d' = min(d, D_max)`` (the bound depth for an
unread pixel) is then gated to the *clear part of the ray*: the goal's z-depth is at most the
depth at which the viewing ray first comes within ``clearance_radius_m`` of any reading (every
reading, not only obstacles under ``T``; for an unread target also the bounding surface itself).
A clear part shorter than ``min_range_m`` leaves no useful goal and is rejected
(``UNREFINED_TARGET_UNSAFE``).

Threshold and ROI per feature source
------------------------------------
``tau`` compares cosine similarities of the feature source that fills ``CandidateGoal.features``:

* ``sim:labels`` (ground-truth instance ids, :mod:`vlm.sim.features` ``perfect``): ~1 inside an
  object, ~0.64 between two instances of one label, ~0 between labels: tau 0.5 separates
  instances and labels;
* ``sim:degraded`` (the benchmark's default): blurred boundaries, texture-driven similarity and
  look-alikes (cos ~0.55-0.7 between a target and its look-alike): tau 0.5 can join a look-alike;
  ``experiments/bench_verifier.py`` measures the off-target rate this costs;
* a Qwen-VL vision tower (``qwen2_5_vl.visual`` / ``qwen3_vl.visual``, post-merger vectors shared
  with the prompt): tau 0.5 is the paper's value and has not been checked on real weights here
  (no weights can be downloaded on this machine); check it on a labelled frame before flying;
* none (the HTTP backend without a local feature source): no threshold; the component is the
  target's surface (above), clipped to the ROI.

The ROI (``roi_px``, 128 px) is in pixels of the depth image for every source; a patch grid
coarser than 16 px gives fewer patches per ROI (8 x 8 at 16 px, 4 x 4 at 32 px).

Clearance ("dilation by r at the local depth")
----------------------------------------------
A pixel ``q`` is *feasible* when its viewing ray -- the straight line from the camera through
``q`` -- passes at least ``clearance_radius_m`` from every obstacle point ``Y_j`` (the
back-projected obstacle pixels). In the image this is exactly the dilation of each obstacle
pixel by the projection of a ball of radius r around its 3D point, whose pixel radius is about
``fx * r / depth_j`` and grows toward the image border; see :func:`planning.verifier.cone_radius_px`.
Because the whole ray clears every obstacle, so does the goal placed on it at any range and the
straight path to it from the camera.

Bearing-aware gating (``sigma_theta``)
--------------------------------------
``d_f = d' * exp(-0.5 * (theta / (sigma_theta * theta_max))^2)``. The range halves at
``|theta| = sqrt(2 ln 2) * sigma_theta * theta_max = 1.177 * sigma_theta * theta_max``. With
the default ``sigma_theta = 0.5`` that is ``0.59 * theta_max`` (26.5 deg for the 90 deg camera),
and at the image edge ``d_f / d' = exp(-2) = 0.135``: 0.95 m from D_max = 7 m, about the 1.2 m
the vehicle covers at v_max = 0.6 m/s while turning theta_max = 45 deg at 0.4 rad/s, so an
edge target makes the vehicle turn first instead of running ahead with the wrong heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["VerifierConfig", "VerifierConfigError"]


class VerifierConfigError(ValueError):
    """A :class:`VerifierConfig` field out of its valid range (the message names the field)."""


@dataclass(frozen=True)
class VerifierConfig:
    """Parameters of the semantic-geometric verifier (frozen, validated on construction).

    Attributes
    ----------
    tau : float
        Cosine-similarity threshold of the semantic mask, in [-1, 1] (paper: 0.5).
    roi_px : int
        Side of the square region of interest centred on the target pixel, pixels; clipped at
        the image border. 128 px is 8 x 8 patches of 16 px and a fifth of a 640 px image: its
        half-width of 64 px is the clearance radius ``fx * r / z`` of an obstacle at 1 m on
        the axis of a camera with fx = 320 px, so a target on the edge of anything from the
        near field outward can be moved clear of it inside the ROI.
    clearance_radius_m : float
        Clearance r of the viewing ray from every obstacle point, metres (paper: 0.2).
    d_max_m : float
        D_max, metres (paper: 7). Refinement is skipped beyond it and ranges are clamped to it.
    sigma_theta : float
        Width of the bearing gate relative to the half horizontal FOV (see the module docs).
    obstacle_depth_m : float
        Near-field depth, metres: every valid reading closer than this is an obstacle.
    foreground_margin_m : float
        Surfaces closer than ``d_ref - foreground_margin_m`` are obstacles (metres; ``inf``
        disables the foreground part of the rule).
    reject_no_reading : bool
        What to do when the target pixel has no depth reading (0, NaN, inf). False (default):
        skip refinement, keep ``p' = p`` and bound its depth by the surface around the hole (see
        "Pixels without a reading are never open space"); the goal stays in front of that
        surface. True: reject every such target with ``RejectionReason.NO_DEPTH_AT_TARGET``.
        Neither setting treats a pixel without a reading as open space.
    surface_jump_ratio : float
        Largest relative depth step between 4-neighbours of one surface (see "The target's
        surface"). 0.1: a ground plane 7 m away seen from 1.5 m with fy = 415 px steps 1.1 % per
        row, 3 % at 20 m; two objects 1.5 m and 3 m away differ by 100 %. Depth noise larger
        than this splits a surface, which only shrinks the region (fewer moves, more
        rejections), never joins two objects. Must be > 0.
    min_range_m : float
        Shortest clear part of the ray that still gives a goal when refinement is skipped,
        metres (default 0.5: below it the planner gains nothing and the pilot keeps its last
        goal). Must be > 0.
    connectivity : int
        Pixel connectivity of the connected components of the semantic mask, 4 or 8. 4 (the
        default) never joins two regions that touch only at a corner.
    radius_class_ratio : float
        The feasibility map groups obstacle pixels into classes whose clearance radii differ by
        at most this ratio; each class is dilated by its largest radius (one distance transform
        per class). Larger is faster and more conservative (the exact check and the pull toward
        the target recover most of it); it never makes the check less safe. Must be > 1.
    """

    tau: float = 0.5
    roi_px: int = 128
    clearance_radius_m: float = 0.2
    d_max_m: float = 7.0
    sigma_theta: float = 0.5
    obstacle_depth_m: float = 2.0
    foreground_margin_m: float = 1.0
    reject_no_reading: bool = False
    connectivity: int = 4
    radius_class_ratio: float = 1.25
    surface_jump_ratio: float = 0.1
    min_range_m: float = 0.5

    def __post_init__(self) -> None:
        def finite(name: str) -> float:
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise VerifierConfigError(f"{name} must be a number, got {value!r}") from None
            if not math.isfinite(value):
                raise VerifierConfigError(f"{name} must be finite, got {value}")
            return value

        tau = finite("tau")
        if not -1.0 <= tau <= 1.0:
            raise VerifierConfigError(f"tau must be in [-1, 1], got {tau}")
        if isinstance(self.roi_px, bool) or not isinstance(self.roi_px, (int,)) or self.roi_px < 1:
            raise VerifierConfigError(f"roi_px must be a positive integer, got {self.roi_px!r}")
        for name in ("clearance_radius_m", "d_max_m", "sigma_theta"):
            if finite(name) <= 0.0:
                raise VerifierConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        if finite("obstacle_depth_m") < 0.0:
            raise VerifierConfigError(f"obstacle_depth_m must be >= 0, got {self.obstacle_depth_m}")
        margin = float(self.foreground_margin_m)
        if math.isnan(margin) or margin < 0.0:
            raise VerifierConfigError(f"foreground_margin_m must be >= 0 (inf allowed), got {self.foreground_margin_m}")
        if not isinstance(self.reject_no_reading, bool):
            raise VerifierConfigError(f"reject_no_reading must be a bool, got {self.reject_no_reading!r}")
        if self.connectivity not in (4, 8):
            raise VerifierConfigError(f"connectivity must be 4 or 8, got {self.connectivity!r}")
        if finite("radius_class_ratio") <= 1.0:
            raise VerifierConfigError(f"radius_class_ratio must be > 1, got {self.radius_class_ratio}")
        for name in ("surface_jump_ratio", "min_range_m"):
            if finite(name) <= 0.0:
                raise VerifierConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("tau", "clearance_radius_m", "d_max_m", "sigma_theta", "obstacle_depth_m", "radius_class_ratio",
                     "surface_jump_ratio", "min_range_m"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "foreground_margin_m", margin)

    def obstacle_threshold_m(self, reference_depth_m: float) -> float:
        """Depth below which a valid reading is an obstacle, metres (the rule in the module docs).

        Parameters
        ----------
        reference_depth_m : float
            ``d_ref = min(depth(p'), d_max_m)`` of the refined pixel (or of the target pixel
            while the search runs).
        """
        return max(self.obstacle_depth_m, float(reference_depth_m) - self.foreground_margin_m)
