"""TUM RGB-D reader: the real 7-Scenes kitchen folder, and constructed folders for association,
interpolation, intrinsics and every malformed piece. Also covers onfly.readers.poses (the
association and interpolation the TUM and bag readers share)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation, Slerp

from onfly.readers.poses import PoseTrack, associate, slerp
from onfly.readers.tum import TUM_DEFAULT_INTRINSICS, TumConfig, TumFormatError, TumReader
from planning.frames import T_BODY_CAM
from realdata_paths import REALDATA

KITCHEN = REALDATA / "7scenes-kitchen-tum"


def _gt_rows(path: Path) -> np.ndarray:
    rows = [list(map(float, line.split())) for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return np.array(rows)


def test_real_kitchen_reads_60_frames_in_metres_with_ground_truth_poses():
    reader = TumReader(KITCHEN)
    assert len(reader) == 60
    assert reader.dropped == {"no_rgb": 0, "no_pose": 0}
    cam = reader.camera
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (640, 480, 585.0, 585.0, 320.0, 240.0)
    gt = _gt_rows(KITCHEN / "groundtruth.txt")
    obs = list(reader)
    assert len(obs) == 60
    np.testing.assert_array_equal([o.t_s for o in obs], gt[:, 0])
    for k in (0, 31, 59):
        o = obs[k]
        png = np.array(Image.open(KITCHEN / "depth" / f"{gt[k, 0]:.6f}.png"))
        assert png.dtype == np.uint16
        assert o.depth_m.dtype == np.float32 and o.depth_m.shape == (480, 640)
        np.testing.assert_array_equal(o.depth_m, png.astype(np.float32) / np.float32(5000.0))
        valid = o.depth_m > 0
        # a Kinect v1 in a kitchen: most pixels read, all within its 0.4-4.5 m range
        assert valid.mean() > 0.5
        assert 0.4 < o.depth_m[valid].min() and o.depth_m[valid].max() < 4.5
        R = Rotation.from_quat(gt[k, 4:8]).as_matrix()  # scipy: scalar-last, like TUM
        np.testing.assert_allclose(o.T_world_cam[:3, :3], R, atol=1e-12)
        np.testing.assert_array_equal(o.T_world_cam[:3, 3], gt[k, 1:4])
        np.testing.assert_array_equal(o.T_body_cam, T_BODY_CAM)
        ref = np.array(Image.open(KITCHEN / "rgb" / f"{gt[k, 0]:.6f}.jpg").convert("RGB")).astype(int)
        assert o.rgb.shape == (480, 640, 3) and o.rgb.dtype == np.uint8
        assert np.abs(o.rgb.astype(int) - ref).mean() < 1.0  # JPEG decoders may differ by a level
    assert len({o.frame_id for o in obs}) == 60
    # the camera moves smoothly: successive positions a few cm apart at 30 Hz
    steps = np.linalg.norm(np.diff([o.T_world_cam[:3, 3] for o in obs], axis=0), axis=1)
    assert steps.max() < 0.05


# -- constructed folders -------------------------------------------------------------------------

W, H = 8, 6


def make_tum(
    root: Path,
    depth_t,
    rgb_t,
    gt_rows,
    *,
    intrinsics: str | None = "100 100 3.5 2.5",
    depth_value: int = 5000,
) -> Path:
    """Write a tiny TUM folder: constant depth PNGs, colour PNGs coding the rgb index in red."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    lines = ["# timestamp filename"]
    for t in depth_t:
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), np.full((H, W), depth_value, np.uint16))
        lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    lines = ["# timestamp filename"]
    for i, t in enumerate(rgb_t):
        img = np.zeros((H, W, 3), np.uint8)
        img[..., 2] = i  # BGR on disk: red channel = index
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), img)
        lines.append(f"{t:.6f}\trgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    (root / "groundtruth.txt").write_text("# t tx ty tz qx qy qz qw\n" + "\n".join(" ".join(f"{v:.9f}" for v in r) for r in gt_rows) + "\n")
    if intrinsics is not None:
        (root / "intrinsics.txt").write_text(f"# fx fy cx cy\n{intrinsics}\n")
    return root


def _identity_gt(times):
    return [[t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0] for t in times]


def test_association_tolerance_pairs_nearest_colour_frame(tmp_path):
    depth_t = [1.0, 1.1, 1.2, 1.3]
    rgb_t = [1.015, 1.125, 1.19, 1.5]  # diffs 15 ms, 25 ms, 10 ms, far
    root = make_tum(tmp_path / "tum", depth_t, rgb_t, _identity_gt([0.9, 1.4]))
    reader = TumReader(root)
    obs = list(reader)
    assert [o.t_s for o in obs] == [1.0, 1.2]
    assert [int(o.rgb[0, 0, 0]) for o in obs] == [0, 2]  # colour index 0 and 2
    assert reader.dropped == {"no_rgb": 2, "no_pose": 0}
    wide = TumReader(root, TumConfig(max_difference_s=0.03))
    assert [o.t_s for o in wide] == [1.0, 1.1, 1.2]


def test_associate_is_greedy_unique_like_tum_associate_py():
    # rgb 0 is the nearest for both depth frames; depth 1 (2 ms) wins it, depth 0 takes its
    # next candidate, rgb 1 at 18 ms; a depth frame with no free candidate stays unmatched
    assert associate([1.000, 1.012], [1.010, 1.018], 0.02) == [(0, 1), (1, 0)]
    assert associate([1.000, 1.012], [1.010, 1.030], 0.02) == [(1, 0)]
    assert associate([0.0, 1.0], [0.5], 0.02) == []
    assert associate([0.0, 1.0], [1.005, 0.011], 0.02, offset_s=-0.01) == [(0, 1), (1, 0)]
    assert associate([], [1.0], 0.02) == []


def test_pose_interpolated_at_depth_time_linear_and_slerp(tmp_path):
    q0 = Rotation.from_euler("xyz", [0.1, -0.2, 0.3])
    q1 = Rotation.from_euler("xyz", [0.4, 0.1, 1.2])
    gt = [
        [0.0, 0.0, 0.0, 0.0, *q0.as_quat()],
        [0.4, 1.0, -2.0, 0.8, *(-q1.as_quat())],  # sign flip: the same rotation; slerp takes the short arc
    ]
    root = make_tum(tmp_path / "tum", [0.1, 0.4], [0.1, 0.4], gt)
    obs = list(TumReader(root))
    u = 0.25
    np.testing.assert_allclose(obs[0].T_world_cam[:3, 3], [u * 1.0, u * -2.0, u * 0.8], atol=1e-12)
    ref = Slerp([0.0, 0.4], Rotation.concatenate([q0, q1]))([0.1]).as_matrix()[0]
    np.testing.assert_allclose(obs[0].T_world_cam[:3, :3], ref, atol=1e-9)
    np.testing.assert_allclose(obs[1].T_world_cam[:3, :3], q1.as_matrix(), atol=1e-9)


def test_frames_without_a_usable_pose_are_dropped(tmp_path):
    # poses at 0, 0.1 and 2.0: the 1.0 frame sits in a 1.9 s gap; 2.015 is 15 ms past the end
    # (within tolerance: end pose); 2.5 is beyond it
    gt = _identity_gt([0.0, 0.1, 2.0])
    gt[2][1] = 5.0
    depth_t = [0.05, 1.0, 2.015, 2.5]
    root = make_tum(tmp_path / "tum", depth_t, depth_t, gt)
    reader = TumReader(root)
    assert reader.dropped == {"no_rgb": 0, "no_pose": 2}
    obs = list(reader)
    assert [o.t_s for o in obs] == [0.05, 2.015]
    assert obs[1].T_world_cam[0, 3] == 5.0
    assert len(TumReader(root, TumConfig(pose_max_gap_s=2.0))) == 3


def test_pose_track_exact_sample_and_slerp_endpoints():
    track = PoseTrack.from_samples([1.0, 0.0, 1.0], [[1, 0, 0], [0, 0, 0], [9, 9, 9]], [[1, 0, 0, 0]] * 3)
    assert list(track.t_s) == [0.0, 1.0]  # sorted, duplicate stamp keeps the first sample
    np.testing.assert_array_equal(track.interpolate(1.0, max_gap_s=5, end_tolerance_s=0)[:3, 3], [1, 0, 0])
    assert track.interpolate(1.5, max_gap_s=5, end_tolerance_s=0.1) is None
    rng = np.random.default_rng(0)
    qa, qb = rng.normal(size=4), rng.normal(size=4)
    qa /= np.linalg.norm(qa)
    qb /= np.linalg.norm(qb)
    np.testing.assert_allclose(slerp(qa, qb, 0.0), qa, atol=1e-12)
    end = slerp(qa, qb, 1.0)
    np.testing.assert_allclose(end * np.sign(end @ qb), qb, atol=1e-12)


def test_intrinsics_option_then_file_then_default(tmp_path, caplog):
    root = make_tum(tmp_path / "a", [0.0], [0.0], _identity_gt([0.0]))
    assert (TumReader(root).camera.fx, TumReader(root).camera.cx) == (100.0, 3.5)
    cam = TumReader(root, TumConfig(intrinsics=(50, 60, 4, 3))).camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (50.0, 60.0, 4.0, 3.0)
    root_b = make_tum(tmp_path / "b", [0.0], [0.0], _identity_gt([0.0]), intrinsics=None)
    # the default is TUM's 640 x 480 calibration: on these 8 x 6 images its principal point
    # (319.5, 239.5) lies off the image, and the reader says so before the first frame
    with caplog.at_level(logging.WARNING, logger="onfly.readers.tum"):
        with pytest.raises(TumFormatError, match=re.escape(f"{TUM_DEFAULT_INTRINSICS} (TUM's default) do not fit its 8 x 6")):
            TumReader(root_b)
    assert "no intrinsics.txt" in caplog.text


def test_depth_scale_is_configurable(tmp_path):
    root = make_tum(tmp_path / "tum", [0.0], [0.0], _identity_gt([0.0]), depth_value=1500)
    assert next(iter(TumReader(root))).depth_m[0, 0] == np.float32(0.3)
    assert next(iter(TumReader(root, TumConfig(depth_scale=1000.0)))).depth_m[0, 0] == np.float32(1.5)


# -- bad input -----------------------------------------------------------------------------------


def test_missing_depth_file_names_file_and_line(tmp_path):
    root = make_tum(tmp_path / "tum", [0.0, 0.1], [0.0, 0.1], _identity_gt([0.0, 0.1]))
    (root / "depth" / "0.100000.png").unlink()
    with pytest.raises(TumFormatError, match=r"depth/0\.100000\.png: missing \(named on .*depth\.txt:3\)"):
        TumReader(root)


def test_malformed_lists_name_file_and_line(tmp_path):
    root = make_tum(tmp_path / "tum", [0.0], [0.0], _identity_gt([0.0]))
    (root / "groundtruth.txt").write_text("# header\n0.0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 1\n")
    with pytest.raises(TumFormatError, match=r"groundtruth\.txt:3: expected 't tx ty tz qx qy qz qw', got 7 fields"):
        TumReader(root)
    (root / "groundtruth.txt").write_text("0.0 1 2 3 0 0 0 0\n")
    with pytest.raises(TumFormatError, match=r"groundtruth\.txt:1: zero quaternion"):
        TumReader(root)
    (root / "groundtruth.txt").unlink()
    with pytest.raises(TumFormatError, match=r"groundtruth\.txt: missing"):
        TumReader(root)
    (root / "groundtruth.txt").write_text("0.0 0 0 0 0 0 0 1\n")
    (root / "depth.txt").write_text("# x\nabc depth/0.000000.png\n")
    with pytest.raises(TumFormatError, match=r"depth\.txt:2: timestamp 'abc' is not a number"):
        TumReader(root)
    (root / "depth.txt").write_text("# nothing\n")
    with pytest.raises(TumFormatError, match=r"depth\.txt: no entries"):
        TumReader(root)


def test_bad_intrinsics_and_bad_depth_png(tmp_path):
    root = make_tum(tmp_path / "tum", [0.0], [0.0], _identity_gt([0.0]), intrinsics="100 100 3.5")
    with pytest.raises(TumFormatError, match=r"intrinsics\.txt:2: expected four numbers 'fx fy cx cy'"):
        TumReader(root)
    (root / "intrinsics.txt").unlink()
    cv2.imwrite(str(root / "depth" / "0.000000.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(TumFormatError, match=r"0\.000000\.png: depth must be a 16-bit single-channel PNG"):
        TumReader(root)


def test_nothing_associates_is_an_error(tmp_path):
    root = make_tum(tmp_path / "tum", [0.0], [0.5], _identity_gt([0.0]))
    with pytest.raises(TumFormatError, match=r"no depth frame has both a colour frame within 0\.02 s and a ground-truth pose"):
        TumReader(root)
    with pytest.raises(TumFormatError, match=r"not a directory"):
        TumReader(tmp_path / "nope")


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match=r"TumConfig\.depth_scale must be positive"):
        TumConfig(depth_scale=0)
    with pytest.raises(ValueError, match=r"TumConfig\.max_difference_s must be positive"):
        TumConfig(max_difference_s=-1)
    with pytest.raises(ValueError, match=r"TumConfig\.intrinsics must be \(fx, fy, cx, cy\)"):
        TumConfig(intrinsics=(1, 2, 3))
