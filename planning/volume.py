"""The operator's flight volume: an axis-aligned box that no goal, guide path or plan leaves.

A real operator flies inside a geofence; in the embedded world the scene's bounds are the
default volume, and ``onfly fly`` / ``onfly replay`` take a box on the command line or in the
config. The volume is an operator feature, not a method's: every method that flies our planner
gets it.

Everything is world ENU, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FlightVolume", "FlightVolumeError"]


class FlightVolumeError(ValueError):
    """A malformed flight volume (names the bad value)."""


@dataclass(frozen=True, eq=False)
class FlightVolume:
    """Axis-aligned box, world ENU, metres.

    Attributes
    ----------
    min_m, max_m : array, shape (3,), metres, world ENU; ``min_m < max_m`` on every axis
    """

    min_m: np.ndarray
    max_m: np.ndarray

    def __post_init__(self) -> None:
        lo = np.asarray(self.min_m, dtype=float).reshape(-1)
        hi = np.asarray(self.max_m, dtype=float).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,):
            raise FlightVolumeError(f"flight volume corners must have shape (3,), got {lo.shape} and {hi.shape}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise FlightVolumeError(f"flight volume corners must be finite, got {lo.tolist()} and {hi.tolist()}")
        if not np.all(hi > lo):
            raise FlightVolumeError(f"flight volume needs min < max on every axis, got min {lo.tolist()} max {hi.tolist()}")
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "min_m", lo)
        object.__setattr__(self, "max_m", hi)

    @classmethod
    def parse(cls, text: str) -> "FlightVolume":
        """From ``"xmin,ymin,zmin,xmax,ymax,zmax"`` (metres, world ENU), the command-line form."""
        try:
            vals = [float(v) for v in text.replace(" ", "").split(",")]
        except ValueError:
            raise FlightVolumeError(f"flight volume {text!r}: expected six numbers xmin,ymin,zmin,xmax,ymax,zmax") from None
        if len(vals) != 6:
            raise FlightVolumeError(f"flight volume {text!r}: expected six numbers xmin,ymin,zmin,xmax,ymax,zmax, got {len(vals)}")
        return cls(np.array(vals[:3]), np.array(vals[3:]))

    def shrunk(self, margin_m: float) -> "FlightVolume":
        """The box moved inward by ``margin_m`` on every face (clipped so it never inverts)."""
        if not (np.isfinite(margin_m) and margin_m >= 0):
            raise FlightVolumeError(f"margin must be finite and >= 0, got {margin_m}")
        mid = 0.5 * (self.min_m + self.max_m)
        half = np.maximum(0.5 * (self.max_m - self.min_m) - margin_m, 1e-3)
        return FlightVolume(mid - half, mid + half)

    def contains(self, points, margin_m: float = 0.0) -> np.ndarray:
        """True where points lie inside the box shrunk by ``margin_m`` (inclusive).

        points : array, shape (n, 3) or (3,), metres, world ENU. Returns bool, shape (n,).
        """
        P = np.atleast_2d(np.asarray(points, dtype=float))
        return np.all((P >= self.min_m + margin_m) & (P <= self.max_m - margin_m), axis=1)

    def clamp(self, points, margin_m: float = 0.0) -> np.ndarray:
        """Nearest points inside the box shrunk by ``margin_m``; same shape as ``points``."""
        box = self.shrunk(margin_m) if margin_m > 0 else self
        P = np.asarray(points, dtype=float)
        return np.clip(P, box.min_m, box.max_m)

    def to_list(self) -> list[float]:
        """``[xmin, ymin, zmin, xmax, ymax, zmax]`` (JSON and logs)."""
        return [*map(float, self.min_m), *map(float, self.max_m)]
