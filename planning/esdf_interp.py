"""Trilinear interpolation of a voxel-centre grid and its gradient (the ESDF's query).

Frames and units: world ENU, metres. Voxel ``(i, j, k)`` of a grid whose local voxel 0 has
global lattice index ``origin_index`` has its centre at ``(origin_index + (i, j, k) + 0.5) *
voxel_m``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["interpolate_grid"]

_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)


def interpolate_grid(grid: np.ndarray, origin_index: np.ndarray, voxel_m: float, points: np.ndarray):
    """Values and gradients of ``grid`` at ``points``, trilinear between voxel centres.

    Parameters
    ----------
    grid : (nx, ny, nz) values at voxel centres, each axis at least 2 long
    origin_index : int (3,), global lattice index of ``grid[0, 0, 0]``
    voxel_m : voxel edge, metres
    points : float (n, 3), world metres, finite

    Returns
    -------
    value : float (n,), the interpolant at the point clamped into the box of voxel centres
    gradient : float (n, 3), per metre, the interpolant's derivative there (piecewise constant
        across cells); zero along an axis on which the point lies outside that box
    excess : float (n, 3), metres from the clamped point to the point (0 inside the box)
    """
    shape = np.asarray(grid.shape, dtype=np.int64)
    strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
    c = points * (1.0 / voxel_m) - (np.asarray(origin_index) + 0.5)
    cc = np.clip(c, 0.0, (shape - 1).astype(float))
    i0 = np.minimum(cc.astype(np.int64), shape - 2)
    f = cc - i0
    idx = (i0 @ strides)[:, None] + _CORNERS @ strides
    vals = grid.reshape(-1)[idx].astype(float).reshape(-1, 2, 2, 2)
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    dz = vals[..., 1] - vals[..., 0]  # (n, 2, 2) over (x, y)
    a = vals[..., 0] + dz * fz[:, None, None]  # interpolated in z, (n, 2, 2)
    ay = a[:, :, 1] - a[:, :, 0]  # (n, 2) over x
    b = a[:, :, 0] + ay * fy[:, None]  # (n, 2) over x
    bx = b[:, 1] - b[:, 0]
    value = b[:, 0] + bx * fx
    dzy = dz[:, :, 0] + (dz[:, :, 1] - dz[:, :, 0]) * fy[:, None]  # (n, 2) over x
    grad = np.empty_like(points, dtype=float)
    grad[:, 0] = bx
    grad[:, 1] = ay[:, 0] + (ay[:, 1] - ay[:, 0]) * fx
    grad[:, 2] = dzy[:, 0] + (dzy[:, 1] - dzy[:, 0]) * fx
    grad *= 1.0 / voxel_m
    excess = (c - cc) * voxel_m
    grad[excess != 0] = 0.0
    return value, grad, excess
