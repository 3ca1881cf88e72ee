"""The distance-field protocol the planner consumes.

Anything that answers signed distance and its gradient at many points is a field: the ESDF
built from depth (:mod:`planning.esdf`), an analytic field of primitives for tests, or a
mesh distance. The planner depends on this protocol only.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["DistanceField"]


@runtime_checkable
class DistanceField(Protocol):
    """Signed Euclidean distance to the nearest obstacle surface.

    ``query(points)`` takes ``points`` of shape (n, 3) in metres, world ENU, and returns
    ``(distance, gradient)``: ``distance`` shape (n,), metres, positive in free space and
    negative inside obstacles; ``gradient`` shape (n, 3), the spatial derivative of distance
    (unit length where the field is a true distance, pointing away from the nearest obstacle).
    """

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
