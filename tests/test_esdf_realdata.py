"""EsdfMap on real Kinect depth with real poses (7-Scenes kitchen, TUM layout).

The data lives in ``../shared/realdata/7scenes-kitchen-tum`` (60 frames, 640 x 480, depth PNG
scale 5000, ``t tx ty tz qx qy qz qw`` camera-to-world). Its world frame is not z-up; the map
must not care. A small local reader keeps planning tests independent of onfly's TUM reader.
"""


import cv2
import numpy as np
import pytest
import scipy.ndimage as ndi

from planning.camera import PinholeCamera
from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig
from planning.frames import make_transform, matrix_from_quat, quat_wxyz_from_xyzw
from realdata_paths import REALDATA

ROOT = REALDATA / "7scenes-kitchen-tum"
CAMERA = PinholeCamera(640, 480, 585.0, 585.0, 320.0, 240.0)
DEPTH_SCALE = 5000.0
# 6 m cube around the middle of the recorded geometry (points span about 2.7 x 2.3 x 2.5 m).
CONFIG = EsdfConfig(size_m=(6.0, 6.0, 6.0))


def _rows(name: str) -> list[list[str]]:
    text = (ROOT / name).read_text()
    return [line.split() for line in text.splitlines() if line.strip() and not line.startswith("#")]


def load_kitchen(quat_order: str = "xyzw"):
    """(depths [(480, 640) float32 m], T_world_cam [(4, 4)]) in file order (same timestamps)."""
    depth_rows, gt_rows = _rows("depth.txt"), _rows("groundtruth.txt")
    assert [r[0] for r in depth_rows] == [r[0] for r in gt_rows]
    depths, poses = [], []
    for d_row, g_row in zip(depth_rows, gt_rows):
        raw = cv2.imread(str(ROOT / d_row[1]), cv2.IMREAD_UNCHANGED)
        assert raw is not None and raw.dtype == np.uint16
        depths.append(raw.astype(np.float32) / DEPTH_SCALE)
        q_file = np.array(g_row[4:8], dtype=float)
        q = quat_wxyz_from_xyzw(q_file) if quat_order == "xyzw" else q_file
        poses.append(make_transform(matrix_from_quat(q), np.array(g_row[1:4], dtype=float)))
    return depths, poses


def _world_points(depth, T, stride=4):
    P_cam, _ = CAMERA.depth_to_points(depth, stride=stride)
    return P_cam @ T[:3, :3].T + T[:3, 3]


def _build(depths, poses) -> tuple[EsdfMap, np.ndarray]:
    # centre: middle of the recorded geometry (from a coarse back-projection)
    P = np.vstack([_world_points(d, T, stride=16) for d, T in zip(depths, poses)])
    center = 0.5 * (np.percentile(P, 1, axis=0) + np.percentile(P, 99, axis=0))
    esdf = EsdfMap(CONFIG)
    for d, T in zip(depths, poses):
        # default config: unknown is an obstacle; the hand-held camera is the "vehicle"
        esdf.integrate(d, CAMERA, T, center_world=center, body_world=T[:3, 3])
    return esdf, center


def _fraction_near_occupied(esdf: EsdfMap, depths, poses) -> float:
    """Share of back-projected points whose voxel or one of its 26 neighbours is occupied."""
    occ = np.zeros(esdf.shape, dtype=bool)
    idx = np.floor(esdf.occupied_points() / esdf.voxel_m).astype(np.int64) - esdf.origin_index
    occ[tuple(idx.T)] = True
    near = ndi.binary_dilation(occ, structure=np.ones((3, 3, 3), dtype=bool))
    hits = total = 0
    for d, T in zip(depths, poses):
        W = _world_points(d, T)
        gi = np.floor(W / esdf.voxel_m).astype(np.int64) - esdf.origin_index
        inside = np.all((gi >= 0) & (gi < np.asarray(esdf.shape)), axis=1)
        assert inside.all(), "the window must cover the recorded geometry"
        hits += int(near[tuple(gi.T)].sum())
        total += len(gi)
    return hits / total


@pytest.fixture(scope="module")
def kitchen():
    if not ROOT.is_dir():
        pytest.fail(f"real data missing: {ROOT}")
    return load_kitchen()


def test_kitchen_cameras_in_free_space_and_points_on_occupied_cells(kitchen):
    depths, poses = kitchen
    assert len(depths) == 60 and depths[0].shape == (480, 640)
    esdf, _ = _build(depths, poses)
    cams = np.array([T[:3, 3] for T in poses])
    # every camera position along the path is free, with room to spare (Kinect sees >= 0.8 m)
    assert np.all(esdf.is_free(cams, margin_m=0.5))
    dist, grad = esdf.query(cams)
    assert np.all(np.isfinite(grad))
    # every frame's depth points land within one voxel of an occupied cell
    frac = _fraction_near_occupied(esdf, depths, poses)
    assert frac >= 0.99, f"only {frac:.3f} of the points lie near an occupied cell"


def test_kitchen_wrong_quaternion_order_is_detected(kitchen):
    """Negative control: reading the TUM quaternion as (w, x, y, z) breaks the consistency."""
    depths, _ = kitchen
    _, bad_poses = load_kitchen(quat_order="wxyz")
    esdf, _ = _build(depths, bad_poses)
    assert _fraction_near_occupied(esdf, depths, bad_poses) < 0.97
