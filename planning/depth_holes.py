"""What bounds a depth image's holes: the readings around a pixel that has none.

A depth camera gives no reading on glass, dark or shiny surfaces, beyond its range, nearer
than its minimum range and, for a stereo camera, where one imager does not see what the other
does. Both the map (:func:`planning.esdf_occupancy.free_reach`: how far a hole's ray clears
free space) and the verifier (:class:`planning.verifier.Verifier`: how far a goal on an unread
target may lie) assume a hole's ray ends at the surface the hole is cut into, found by one rule
(:func:`hole_bounds`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["hole_bounds"]


def _nearest_reading_along(d: np.ndarray, valid: np.ndarray, axis: int, reverse: bool) -> np.ndarray:
    """Per pixel, the first valid value of ``d`` met scanning along ``axis`` (the pixel itself
    included), toward lower indices or, with ``reverse``, higher ones; inf where none."""
    n = d.shape[axis]
    shape = [1, 1]
    shape[axis] = n
    pos = np.arange(n, dtype=np.int32).reshape(shape)
    if reverse:
        idx = np.where(valid, pos, np.int32(n))
        last = np.flip(np.minimum.accumulate(np.flip(idx, axis=axis), axis=axis), axis=axis)
        found = last < n
    else:
        idx = np.where(valid, pos, np.int32(-1))
        last = np.maximum.accumulate(idx, axis=axis)
        found = last >= 0
    out = np.take_along_axis(d, np.clip(last, 0, n - 1), axis=axis)
    return np.where(found, out, np.float32(np.inf))


def hole_bounds(depth_m: np.ndarray, valid: np.ndarray, needs_below: bool) -> np.ndarray:
    """The reading that bounds each pixel's ray when the pixel has none: the nearest of the
    first readings met scanning its row and column outward, left, right, up and down.

    A hole cut into a surface (glass, a dark patch, a far target beyond the sensor's range
    above readable ground) has that surface on its row and column, so its ray is assumed to
    end there. With ``needs_below`` a pixel whose column holds no reading below it is
    unbounded: a hole that runs out of the image's bottom edge may be an object nearer than
    the sensor's minimum range, whose readings above are the surface behind it.

    Parameters
    ----------
    depth_m : float32 (h, w), metres, read only where ``valid``
    valid : bool (h, w), the pixels holding a reading
    needs_below : the rule above

    Returns
    -------
    float32 (h, w), metres: the bound (the pixel's own reading where it has one); inf where
    nothing bounds the pixel
    """
    nb = _nearest_reading_along(depth_m, valid, 1, False)
    np.minimum(nb, _nearest_reading_along(depth_m, valid, 1, True), out=nb)
    np.minimum(nb, _nearest_reading_along(depth_m, valid, 0, False), out=nb)
    below = _nearest_reading_along(depth_m, valid, 0, True)  # down the image: higher rows
    np.minimum(nb, below, out=nb)
    if needs_below:
        nb[~np.isfinite(below)] = np.inf  # nothing read below: unbounded
    return nb
