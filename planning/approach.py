"""A goal in front of a target that no straight viewing ray reaches with clearance.

The verifier (:mod:`planning.verifier`) accepts a pixel only when its straight viewing ray keeps
the clearance radius from every reading in front of the target. When something stands between
the camera and the target (a parked car before a wall charger, a desk's edge before a lamp on a
lower desk), every pixel of the target fails and the decision is rejected, although the
planner's guide search (:mod:`planning.guide_path`) flies around what is in between. Without a
goal the vehicle hovers where it is, with the target in view, until something else gives up.

:func:`approach_point` gives that route its goal: the point nearest the target, on the
vehicle's side of it, that the map has *seen* free and that keeps a clearance from every
obstacle (the planner's safety distance). It tries the straight way back toward the vehicle
first, then ways turned to either side about the target (up to ``max_turn_rad``), so a target
hemmed in on the near side (a charger between two cars) is approached from beside. It never
returns a point in unknown space, outside the flight volume, or not nearer the target than
the vehicle already is.

Everything is in world ENU metres.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["approach_point"]


def approach_point(
    target_world,
    from_world,
    field,
    *,
    clearance_m: float,
    standoff_m: float,
    reach_m: float = 2.0,
    step_m: float = 0.25,
    max_turn_rad: float = math.pi / 2,
    turn_step_rad: float = math.pi / 6,
    min_travel_m: float = 0.5,
    z_min_m: float | None = None,
    volume=None,
    volume_margin_m: float = 0.0,
) -> np.ndarray | None:
    """The free point nearest ``target_world`` on the way from ``from_world``, or None.

    Parameters
    ----------
    target_world : (3,) metres, world ENU: the target's visible surface point
    from_world : (3,) metres, world ENU: where the vehicle is
    field : a distance field with ``query(points) -> (distance, gradient)``; when it also has
        ``observed_free(points)`` (:class:`planning.esdf.EsdfMap`), candidates must be seen free
    clearance_m : the distance every candidate keeps from obstacles (the field's distance),
        metres
    standoff_m : the nearest a candidate may be to the target, horizontally, metres
    reach_m : candidates lie from ``standoff_m`` to ``standoff_m + reach_m`` from the target
    step_m : spacing of the candidates along one way, metres
    max_turn_rad, turn_step_rad : the ways tried turn about the target from the bearing
        toward the vehicle by 0, +-1, +-2, ... steps, up to the maximum
    min_travel_m : a candidate must be this much nearer the target (horizontally) than
        ``from_world`` is; less is no progress
    z_min_m : altitude floor for the candidate (the pilot's goal floor), or None
    volume : optional flight volume (``contains(points, margin_m)``); candidates stay inside it
        shrunk by ``volume_margin_m``

    Returns
    -------
    (3,) metres, world ENU, at the target's altitude (raised to ``z_min_m``), or None when no
    candidate passes.
    """
    target = np.asarray(target_world, dtype=float).reshape(3)
    start = np.asarray(from_world, dtype=float).reshape(3)
    if not (np.isfinite(target).all() and np.isfinite(start).all()):
        return None
    if not (clearance_m >= 0 and standoff_m >= 0 and reach_m >= 0 and step_m > 0 and turn_step_rad > 0):
        raise ValueError("approach_point: clearance, standoff and reach must be >= 0, the steps > 0")
    delta = start[:2] - target[:2]
    d_start = float(np.hypot(*delta))
    if d_start < standoff_m + min_travel_m:
        return None
    bearing = float(np.arctan2(delta[1], delta[0]))
    z = target[2] if z_min_m is None else max(target[2], float(z_min_m))
    ranges = standoff_m + np.arange(0.0, reach_m + 1e-9, step_m)
    k_max = int(math.floor(max_turn_rad / turn_step_rad + 1e-9))
    turns = [0.0] + [s * k * turn_step_rad for k in range(1, k_max + 1) for s in (1.0, -1.0)]
    seen_free = getattr(field, "observed_free", None)
    for turn in turns:
        a = bearing + turn
        pts = np.column_stack([target[0] + ranges * math.cos(a), target[1] + ranges * math.sin(a), np.full(ranges.size, z)])
        ok = ranges <= d_start - min_travel_m  # nearer the target than the vehicle is
        dist, _ = field.query(pts)
        ok &= dist >= clearance_m
        if seen_free is not None:
            ok &= np.asarray(seen_free(pts), bool)
        if volume is not None:
            ok &= np.asarray(volume.contains(pts, margin_m=volume_margin_m), bool)
        hits = np.flatnonzero(ok)
        if hits.size:
            return pts[hits[0]].copy()
    return None
