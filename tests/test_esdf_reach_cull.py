"""The ESDF's clearing shortcuts (``EsdfConfig.reach_cull``) change nothing but the cost.

- the map with the shortcuts equals the map without them voxel for voxel (log-odds, observed,
  obstacle mask, distance) after every frame of constructed sequences: a wall with a hole, open
  ground under the sky, a frame without any reading, a cluttered random scene with holes;
- the pieces against brute force: the reach upper bound is an upper bound and exact on
  readings, the per-pixel hole reach equals :func:`free_reach`, the tile maximum equals the
  maximum over its tiles, and a block the cull drops holds no voxel centre that the frame passes
  through.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from planning.camera import PinholeCamera
from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig, EsdfConfigError
from planning.esdf_occupancy import _BLOCK, _TILE, _hole_reach, _reach_upper, _TileMax, free_reach
from planning.frames import body_transform, cam_transform_from_body

CAMERA = PinholeCamera.from_fov(160, 120, 90.0, 60.0)
CFG = EsdfConfig(size_m=(8.0, 8.0, 4.0))


def _pose(p, yaw) -> np.ndarray:
    return cam_transform_from_body(body_transform(np.asarray(p, float), yaw))


def _wall_with_hole(T: np.ndarray) -> np.ndarray:
    """z-depth of the wall x = 4 (world) seen from T, with no reading on a 1 x 0.6 m patch."""
    rays = CAMERA.rays() @ T[:3, :3].T
    o = T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rays[..., 0] > 1e-6, (4.0 - o[0]) / rays[..., 0], np.inf)
    hit = o + rays * t[..., None]
    depth = t.astype(np.float32)
    hole = (np.abs(hit[..., 1] - 0.3) < 0.5) & (np.abs(hit[..., 2] - 1.5) < 0.3)
    depth[hole] = 0.0
    return depth


def _ground_and_sky(T: np.ndarray) -> np.ndarray:
    rays = CAMERA.rays() @ T[:3, :3].T
    with np.errstate(divide="ignore"):
        t = np.where(rays[..., 2] < -1e-6, -T[2, 3] / rays[..., 2], np.inf)
    depth = t.astype(np.float32)
    depth[np.isfinite(depth) & (depth > 6.0)] = 0.0  # a D435-like range cut
    return depth


def _random_holes(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    depth = rng.uniform(0.5, 9.0, CAMERA.shape).astype(np.float32)
    # smooth blobs: coarse random depth, upsampled, with holes in patches
    coarse = rng.uniform(0.8, 8.0, (12, 16)).astype(np.float32)
    depth = np.kron(coarse, np.ones((10, 10), np.float32))
    patches = np.kron(rng.random((12, 16)) < 0.3, np.ones((10, 10), bool))
    depth[patches] = rng.choice(np.array([0.0, np.nan, np.inf], np.float32))
    return depth


def _sequences():
    rng = np.random.default_rng(7)
    path = [(-0.5 + 0.35 * k, 0.1 * np.sin(k), 1.5) for k in range(8)]
    yaws = [0.25 * np.sin(0.7 * k) for k in range(8)]
    poses = [_pose(p, y) for p, y in zip(path, yaws)]
    yield "wall with a hole", [(_wall_with_hole(T), T) for T in poses]
    yield "ground under the sky", [(_ground_and_sky(T), T) for T in poses]
    yield "no reading at all, then readings", [(np.zeros(CAMERA.shape, np.float32), poses[0])] + [
        (_wall_with_hole(T), T) for T in poses[1:4]
    ]
    yield "random holes", [(_random_holes(T, rng), T) for T in poses]


@pytest.mark.parametrize("name,frames", list(_sequences()), ids=[n for n, _ in _sequences()])
def test_the_shortcuts_leave_the_map_unchanged(name, frames):
    fast = EsdfMap(CFG)
    slow = EsdfMap(dataclasses.replace(CFG, reach_cull=False))
    assert fast.config.reach_cull and not slow.config.reach_cull
    cleared = 0
    for depth, T in frames:
        uf = fast.integrate(depth, CAMERA, T)
        us = slow.integrate(depth, CAMERA, T)
        assert uf.n_miss_voxels == us.n_miss_voxels
        cleared += us.n_miss_voxels
        a, b = fast._occ, slow._occ
        assert np.array_equal(a.logodds, b.logodds)
        assert np.array_equal(a.observed, b.observed)
        assert np.array_equal(a.solid, b.solid)
        assert np.array_equal(fast.distance_grid, slow.distance_grid)
    assert cleared > 1000  # the sequences do clear space (the comparison is not vacuous)


def test_reach_cull_must_be_a_bool():
    with pytest.raises(EsdfConfigError, match="reach_cull"):
        EsdfConfig(reach_cull=1)


def test_reach_upper_bound_and_hole_reach_against_free_reach():
    rng = np.random.default_rng(3)
    specials = np.array([0.0, np.nan, np.inf, -1.0, 0.01], np.float32)
    for trial in range(60):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        depth = rng.uniform(0.0, 12.0, (h, w)).astype(np.float32)
        depth[rng.random((h, w)) < rng.uniform(0.0, 1.0)] = rng.choice(specials)
        for cfg in (CFG, dataclasses.replace(CFG, no_reading_clear_m=0.0)):
            full, valid = free_reach(depth, cfg)
            upper, valid2, clipped = _reach_upper(depth, cfg)
            assert np.array_equal(valid, valid2)
            assert np.all(upper >= full), trial
            assert np.array_equal(upper[valid], full[valid])
            r, c = np.nonzero(~valid)
            if r.size and valid.any() and cfg.no_reading_clear_m > 0:
                np.testing.assert_array_equal(_hole_reach(clipped, valid, r, c, cfg), full[r, c])


def test_tile_max_is_the_max_over_the_touched_tiles():
    rng = np.random.default_rng(5)
    img = rng.normal(size=(61, 83)).astype(np.float32)
    table = _TileMax(img)
    r0 = rng.integers(0, 61, 300)
    r1 = np.minimum(r0 + rng.integers(0, 61, 300), 60)
    c0 = rng.integers(0, 83, 300)
    c1 = np.minimum(c0 + rng.integers(0, 83, 300), 82)
    got = table.query(r0, r1, c0, c1)
    for k in range(300):
        tr0, tr1 = (r0[k] // _TILE) * _TILE, (r1[k] // _TILE + 1) * _TILE
        tc0, tc1 = (c0[k] // _TILE) * _TILE, (c1[k] // _TILE + 1) * _TILE
        assert got[k] == img[tr0:tr1, tc0:tc1].max()
        assert got[k] >= img[r0[k] : r1[k] + 1, c0[k] : c1[k] + 1].max()


def test_a_culled_block_holds_no_voxel_the_frame_passes_through():
    """Brute force over every voxel centre of every block: where the cull says "beyond reach",
    no centre projects to a pixel whose reach exceeds its z-depth."""
    occ = EsdfMap(CFG)._occ
    rng = np.random.default_rng(11)
    n_culled = 0
    for trial in range(6):
        T = _pose((rng.uniform(-1, 1), rng.uniform(-1, 1), 1.5), rng.uniform(-np.pi, np.pi))
        depth = _random_holes(T, rng) if trial % 2 else _wall_with_hole(T)
        occ.origin_index = occ.origin_for_center(T[:3, 3])
        reach, _ = free_reach(depth, CFG)
        upper, _, _ = _reach_upper(depth, CFG)
        nb = np.asarray(CFG.grid_shape) // _BLOCK
        axes = [(occ.origin_index[k] + (np.arange(nb[k]) + 0.5) * _BLOCK) * CFG.voxel_m for k in range(3)]
        centers = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        culled = occ._beyond_reach(CAMERA, T, centers, upper)
        offs = (np.arange(_BLOCK) - (_BLOCK - 1) / 2) * CFG.voxel_m
        local = np.stack(np.meshgrid(offs, offs, offs, indexing="ij"), axis=-1).reshape(-1, 3)
        for c in centers[culled]:
            P = (c + local - T[:3, 3]) @ T[:3, :3]
            z = P[:, 2]
            front = z > CFG.min_range_m
            u = np.floor(CAMERA.fx * P[front, 0] / z[front] + CAMERA.cx + 0.5).astype(int)
            v = np.floor(CAMERA.fy * P[front, 1] / z[front] + CAMERA.cy + 0.5).astype(int)
            inside = (u >= 0) & (u < CAMERA.width) & (v >= 0) & (v < CAMERA.height)
            assert not np.any(z[front][inside] < reach[v[inside], u[inside]])
        n_culled += int(culled.sum())
    assert n_culled > 50  # the cull does drop blocks
