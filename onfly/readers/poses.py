"""Timestamp association and pose interpolation shared by the TUM and bag readers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planning.frames import make_transform, matrix_from_quat

__all__ = ["associate", "slerp", "PoseTrack"]


def associate(t_a, t_b, max_difference_s: float, offset_s: float = 0.0) -> list[tuple[int, int]]:
    """Match two timestamp lists, as TUM's ``associate.py`` does.

    Every pair with ``|t_a[i] - (t_b[j] + offset_s)| < max_difference_s`` is a candidate;
    candidates are taken greedily from the smallest difference, each index at most once.

    Parameters
    ----------
    t_a, t_b : arrays, shape (n,) and (m,), seconds (any order)
    max_difference_s : association tolerance, seconds (TUM default 0.02)
    offset_s : added to ``t_b`` before matching

    Returns
    -------
    list of ``(i, j)`` index pairs sorted by ``t_a[i]`` (ties by ``i``)
    """
    t_a = np.asarray(t_a, dtype=float).reshape(-1)
    t_b = np.asarray(t_b, dtype=float).reshape(-1) + offset_s
    if t_a.size == 0 or t_b.size == 0:
        return []
    order_b = np.argsort(t_b, kind="stable")
    sorted_b = t_b[order_b]
    lo = np.searchsorted(sorted_b, t_a - max_difference_s, side="left")
    hi = np.searchsorted(sorted_b, t_a + max_difference_s, side="right")
    diffs, ii, jj = [], [], []
    for i in range(t_a.size):
        for k in range(lo[i], hi[i]):
            d = abs(t_a[i] - sorted_b[k])
            if d < max_difference_s:
                diffs.append(d)
                ii.append(i)
                jj.append(int(order_b[k]))
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for k in np.lexsort((np.asarray(jj), np.asarray(ii), np.asarray(diffs))) if diffs else []:
        i, j = ii[k], jj[k]
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append((i, j))
    pairs.sort(key=lambda p: (t_a[p[0]], p[0]))
    return pairs


def slerp(q0, q1, u: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions ``(w, x, y, z)`` along the short arc.

    ``u = 0`` gives ``q0``, ``u = 1`` gives ``q1`` (or ``-q1``, the same rotation).
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
    else:
        theta = np.arccos(min(d, 1.0))
        q = (np.sin((1.0 - u) * theta) * q0 + np.sin(u * theta) * q1) / np.sin(theta)
    return q / np.linalg.norm(q)


@dataclass(frozen=True, eq=False)
class PoseTrack:
    """Timestamped poses, interpolated on demand.

    Attributes
    ----------
    t_s : array (n,), seconds, strictly increasing (duplicates removed at construction)
    p : array (n, 3), metres, position of the posed frame in the parent frame
    q_wxyz : array (n, 4), unit quaternions, rotation posed frame -> parent frame
    """

    t_s: np.ndarray
    p: np.ndarray
    q_wxyz: np.ndarray

    @classmethod
    def from_samples(cls, t_s, p, q_wxyz) -> "PoseTrack":
        """Sort by time; keep the first of samples with equal timestamps. Quaternions are normalized."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        p = np.asarray(p, dtype=float).reshape(-1, 3)
        q = np.asarray(q_wxyz, dtype=float).reshape(-1, 4)
        if not (t.size == p.shape[0] == q.shape[0]):
            raise ValueError(f"pose track sizes differ: t {t.size}, p {p.shape[0]}, q {q.shape[0]}")
        order = np.argsort(t, kind="stable")
        t, p, q = t[order], p[order], q[order]
        keep = np.ones(t.size, dtype=bool)
        keep[1:] = np.diff(t) > 0
        norms = np.linalg.norm(q, axis=1, keepdims=True)
        return cls(t[keep], p[keep], q[keep] / norms[keep])

    def __len__(self) -> int:
        return int(self.t_s.size)

    def transform_at_index(self, k: int) -> np.ndarray:
        """Stored pose ``k`` as a 4x4 transform (parent <- posed frame)."""
        return make_transform(matrix_from_quat(self.q_wxyz[k]), self.p[k])

    def interpolate(self, t_s: float, *, max_gap_s: float, end_tolerance_s: float) -> np.ndarray | None:
        """Pose at ``t_s``: linear in position, slerp in rotation, between the two samples around it.

        A sample at exactly ``t_s`` is returned as stored. Returns None when the two
        bracketing samples are more than ``max_gap_s`` apart, or ``t_s`` lies outside the
        track by more than ``end_tolerance_s`` (within it, the end sample is used).

        Returns
        -------
        array (4, 4) or None
        """
        n = len(self)
        if n == 0:
            return None
        k = int(np.searchsorted(self.t_s, t_s, side="left"))
        if k < n and self.t_s[k] == t_s:
            return self.transform_at_index(k)
        if k == 0:
            return self.transform_at_index(0) if self.t_s[0] - t_s <= end_tolerance_s else None
        if k == n:
            return self.transform_at_index(n - 1) if t_s - self.t_s[-1] <= end_tolerance_s else None
        t0, t1 = self.t_s[k - 1], self.t_s[k]
        if t1 - t0 > max_gap_s:
            return None
        u = (t_s - t0) / (t1 - t0)
        p = (1.0 - u) * self.p[k - 1] + u * self.p[k]
        q = slerp(self.q_wxyz[k - 1], self.q_wxyz[k], u)
        return make_transform(matrix_from_quat(q), p)
