"""Tests of planning.verifier: constructed images with exact answers, a seeded property test on
random box scenes, and real Kinect depth (7-Scenes kitchen).

Safety is always checked by brute force, independently of the verifier: every valid depth pixel
that the documented obstacle rule classes as an obstacle is back-projected, and the returned goal
(and the straight path to it from the camera) must keep at least r from all of them.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from planning.camera import PinholeCamera
from realdata_paths import REALDATA
from planning.frames import body_transform, cam_transform_from_body, invert_transform, transform_points
from planning.verifier import (
    CandidateGoal,
    RefinementNote,
    RejectionReason,
    Verifier,
    VerifierConfig,
    VerifierConfigError,
    VerifierInputError,
    bearing_gate,
    cone_radius_px,
)

R_M = 0.2
KITCHEN = REALDATA / "7scenes-kitchen-tum"

# -- helpers -----------------------------------------------------------------------------------


def square_camera() -> PinholeCamera:
    """640 x 480, fx = fy = 320 (90 deg horizontal FOV), integer principal point (320, 240)."""
    return PinholeCamera(640, 480, 320.0, 320.0, 320.0, 240.0)


def onehot_features(labels: np.ndarray, patch: int, n_labels: int) -> np.ndarray:
    """One-hot label vectors averaged over each patch x patch block, shape (Hp, Wp, n_labels)."""
    h, w = labels.shape
    onehot = np.eye(n_labels)[labels]
    return onehot.reshape(h // patch, patch, w // patch, patch, n_labels).mean(axis=(1, 3))


def random_label_features(labels: np.ndarray, patch: int, dim: int, seed: int) -> np.ndarray:
    """A seeded random unit vector per label (label -1 included), averaged over each patch."""
    rng = np.random.default_rng(seed)
    vec = rng.normal(size=(int(labels.max()) + 2, dim))
    vec /= np.linalg.norm(vec, axis=1, keepdims=True)
    pix = vec[labels + 1]
    h, w = labels.shape
    return pix.reshape(h // patch, patch, w // patch, patch, dim).mean(axis=(1, 3))


def render_boxes(camera: PinholeCamera, boxes, no_hit: float = np.nan) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast axis-aligned boxes given in the camera optical frame.

    boxes : list of (lo (3,), hi (3,)) corners in metres. Returns z-depth (H, W) float32 with
    ``no_hit`` where no box is hit, and labels (H, W) int (box index, -1 for no hit). Rays have
    z = 1, so the ray parameter is the z-depth.
    """
    rays = camera.rays()
    depth = np.full(camera.shape, np.inf)
    labels = np.full(camera.shape, -1, dtype=int)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / rays
        for k, (lo, hi) in enumerate(boxes):
            t1 = np.asarray(lo, float) * inv
            t2 = np.asarray(hi, float) * inv
            t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
            t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < depth)
            depth[hit] = t_near[hit]
            labels[hit] = k
    depth[~np.isfinite(depth)] = no_hit
    return depth.astype(np.float32), labels


def rule_threshold(config: VerifierConfig, depth: np.ndarray, uv) -> float:
    """The documented obstacle threshold at pixel uv, computed here from the config docs."""
    col, row = int(math.floor(uv[0] + 0.5)), int(math.floor(uv[1] + 0.5))
    d = float(depth[row, col])
    ref = min(d, config.d_max_m) if (math.isfinite(d) and d > 0) else config.d_max_m
    return max(config.obstacle_depth_m, ref - config.foreground_margin_m)


def surface_bruteforce(depth: np.ndarray, uv, ratio: float, band_m: float) -> np.ndarray:
    """The target's surface by graph components (scipy), independently of the verifier's flood
    fill: 4-neighbours with readings within band_m of the seed, |ln z_a - ln z_b| <= ln(1 + ratio)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    col, row = int(math.floor(uv[0] + 0.5)), int(math.floor(uv[1] + 0.5))
    z = depth.astype(np.float64)
    d = z[row, col]
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(z) & (z > 0) & (np.abs(z - d) <= band_m)
        lz = np.log(np.where(ok, z, 1.0))
    h, w = z.shape
    idx = np.arange(h * w).reshape(h, w)
    tol = math.log1p(ratio) + 1e-6
    pairs = []
    for a, b, la, lb, oa, ob in (
        (idx[:, :-1], idx[:, 1:], lz[:, :-1], lz[:, 1:], ok[:, :-1], ok[:, 1:]),
        (idx[:-1], idx[1:], lz[:-1], lz[1:], ok[:-1], ok[1:]),
    ):
        e = oa & ob & (np.abs(la - lb) <= tol)
        pairs.append((a[e], b[e]))
    i = np.concatenate([p[0] for p in pairs])
    j = np.concatenate([p[1] for p in pairs])
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(h * w, h * w))
    _, lab = connected_components(graph, directed=False)
    lab = lab.reshape(h, w)
    return (lab == lab[row, col]) & ok


def rule_obstacles(config: VerifierConfig, depth: np.ndarray, target_uv, refined_uv, camera) -> np.ndarray:
    """Obstacle points of the documented rule evaluated at the refined pixel: readings closer than
    T(refined depth), except the target's surface at or beyond d_ref - margin."""
    T = rule_threshold(config, depth, refined_uv)
    col, row = int(math.floor(refined_uv[0] + 0.5)), int(math.floor(refined_uv[1] + 0.5))
    d_ref = min(float(depth[row, col]), config.d_max_m)
    z = depth.astype(np.float64)
    with np.errstate(invalid="ignore"):
        obst = np.isfinite(z) & (z > 0) & (z < T)
        if config.obstacle_depth_m > d_ref - config.foreground_margin_m:
            surf = surface_bruteforce(depth, target_uv, config.surface_jump_ratio, config.foreground_margin_m)
            obst &= ~(surf & (z >= d_ref - config.foreground_margin_m))
    return camera.rays()[obst] * z[obst][:, None]


def obstacle_points(camera: PinholeCamera, depth: np.ndarray, threshold_m: float) -> np.ndarray:
    """Back-projected obstacle pixels (valid reading < threshold), shape (n, 3), optical frame."""
    d = depth.astype(np.float64)
    with np.errstate(invalid="ignore"):
        obst = np.isfinite(d) & (d > 0) & (d < threshold_m)
    return camera.rays()[obst] * d[obst][:, None]


def reading_points(camera: PinholeCamera, depth: np.ndarray) -> np.ndarray:
    """Every reading, back-projected (n, 3)."""
    return obstacle_points(camera, depth, np.inf)


def point_clearance(P: np.ndarray, X: np.ndarray) -> float:
    return float(np.min(np.linalg.norm(P - X, axis=1))) if len(P) else math.inf


def segment_clearance(P: np.ndarray, X: np.ndarray) -> float:
    """Distance from the points to the segment camera centre -> X."""
    if not len(P):
        return math.inf
    t = np.clip(P @ X / (X @ X), 0.0, 1.0)
    return float(np.min(np.linalg.norm(P - t[:, None] * X[None, :], axis=1)))


def ray_clearance(P: np.ndarray, camera: PinholeCamera, uv) -> float:
    """Distance from the points to the half-line from the camera through pixel uv."""
    if not len(P):
        return math.inf
    d = camera.back_project(np.asarray(uv, float), 1.0)
    d = d / np.linalg.norm(d)
    t = np.maximum(P @ d, 0.0)
    return float(np.min(np.linalg.norm(P - t[:, None] * d[None, :], axis=1)))


def candidate(uv, depth, camera, features=None, patch=16.0, T=None) -> CandidateGoal:
    return CandidateGoal(uv, depth, features, patch, np.eye(4) if T is None else T, camera)


def edge_scene(target_depth: float, obstacle_depth: float, edge_col: int = 336):
    """Wall at ``target_depth`` (label 0) with an obstacle (label 1) at ``obstacle_depth`` for
    columns >= edge_col, on the square camera. Returns camera, depth, labels, one-hot features."""
    cam = square_camera()
    depth = np.full(cam.shape, target_depth, dtype=np.float32)
    labels = np.zeros(cam.shape, dtype=int)
    depth[:, edge_col:] = obstacle_depth
    labels[:, edge_col:] = 1
    return cam, depth, labels


def exact_nearest_feasible(cam, depth, labels, uv, label, roi, threshold_m) -> float:
    """Brute force: distance from uv to the nearest pixel of ``label`` inside ``roi`` whose ray
    clears every obstacle point by r, searched on the rows of uv +- 2 (the obstacle in the
    callers is a vertical edge to the right, so on each row clearance grows leftward)."""
    P = obstacle_points(cam, depth, threshold_m)
    r0, r1, c0, c1 = roi
    best = math.inf
    for row in range(max(r0, int(uv[1]) - 2), min(r1, int(uv[1]) + 3)):
        for col in range(c1 - 1, c0 - 1, -1):
            if labels[row, col] == label and ray_clearance(P, cam, (col, row)) >= R_M:
                best = min(best, math.hypot(col - uv[0], row - uv[1]))
                break
    return best


def assert_safe(result, cand: CandidateGoal, config: VerifierConfig) -> None:
    """The returned goal and the path to it clear every rule obstacle by r (brute force).

    Refined goals: the rule evaluated at the refined pixel. Skipped refinement (far or unread
    target): every reading, and an unread target's goal stays in front of its bounding surface."""
    assert result.accepted and result.goal_world is not None
    rec = result.record
    X_cam = transform_points(invert_transform(cand.T_world_cam), result.goal_world)
    if rec.refinement_ran:
        assert rec.ray_clearance_m > config.clearance_radius_m
        P = rule_obstacles(config, cand.depth_m, cand.pixel_uv, rec.refined_uv, cand.camera)
        assert rec.obstacle_threshold_m == pytest.approx(rule_threshold(config, cand.depth_m, rec.refined_uv))
        if math.isfinite(rec.clear_range_m):  # a near target's goal clears every reading
            assert X_cam[2] <= rec.clear_range_m + 1e-9
            assert segment_clearance(reading_points(cand.camera, cand.depth_m), X_cam) >= config.clearance_radius_m - 1e-9
    else:
        P = reading_points(cand.camera, cand.depth_m)
        assert X_cam[2] <= rec.clear_range_m + 1e-9
        if rec.refinement_note is RefinementNote.NO_DEPTH_READING:
            assert X_cam[2] <= rec.bound_depth_m - config.clearance_radius_m * 0.5
    assert point_clearance(P, X_cam) >= config.clearance_radius_m - 1e-9
    assert segment_clearance(P, X_cam) >= config.clearance_radius_m - 1e-9


# -- configuration and input validation ----------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("tau", 1.5),
        ("tau", float("nan")),
        ("roi_px", 0),
        ("roi_px", 12.5),
        ("clearance_radius_m", 0.0),
        ("d_max_m", -1.0),
        ("sigma_theta", 0.0),
        ("obstacle_depth_m", -0.1),
        ("foreground_margin_m", -1.0),
        ("reject_no_reading", 1),
        ("connectivity", 6),
        ("radius_class_ratio", 1.0),
        ("surface_jump_ratio", 0.0),
        ("min_range_m", -1.0),
    ],
)
def test_config_rejects_bad_field(field, value):
    with pytest.raises(VerifierConfigError, match=field):
        VerifierConfig(**{field: value})


def test_config_defaults_and_threshold_rule():
    cfg = VerifierConfig()
    assert (cfg.tau, cfg.clearance_radius_m, cfg.d_max_m, cfg.sigma_theta) == (0.5, 0.2, 7.0, 0.5)
    assert cfg.obstacle_threshold_m(5.0) == pytest.approx(4.0)  # foreground part
    assert cfg.obstacle_threshold_m(2.5) == pytest.approx(2.0)  # near-field part
    assert VerifierConfig(foreground_margin_m=math.inf).obstacle_threshold_m(7.0) == 2.0


def test_candidate_validation_names_the_field():
    cam = square_camera()
    depth = np.full(cam.shape, 5.0, np.float32)
    feats = np.zeros((30, 40, 3))
    with pytest.raises(VerifierInputError, match="depth_m must have shape"):
        CandidateGoal((1, 1), depth[:, :-1], None, 16, np.eye(4), cam)
    with pytest.raises(VerifierInputError, match="features grid must be"):
        CandidateGoal((1, 1), depth, feats[:, :-1], 16, np.eye(4), cam)
    with pytest.raises(VerifierInputError, match="features grid must be"):
        CandidateGoal((1, 1), depth, feats, 20, np.eye(4), cam)
    with pytest.raises(VerifierInputError, match="features must have shape"):
        CandidateGoal((1, 1), depth, feats[..., 0], 16, np.eye(4), cam)
    with pytest.raises(VerifierInputError, match="patch_px"):
        CandidateGoal((1, 1), depth, feats, 0.0, np.eye(4), cam)
    with pytest.raises(VerifierInputError, match="T_world_cam"):
        CandidateGoal((1, 1), depth, feats, 16, np.eye(3), cam)
    with pytest.raises(VerifierInputError, match="pixel_uv"):
        CandidateGoal((1, 2, 3), depth, feats, 16, np.eye(4), cam)
    with pytest.raises(VerifierInputError, match="camera"):
        CandidateGoal((1, 1), depth, feats, 16, np.eye(4), "camera")
    # A non-integer patch size whose grid covers the image is accepted (e.g. 23 patches of 640/23).
    CandidateGoal((1, 1), depth, np.zeros((18, 23, 2)), 640 / 23, np.eye(4), cam)


# -- step 1: refinement on constructed images ------------------------------------------------------


def test_feasible_pixel_stays_put_exactly():
    cam, depth, labels = edge_scene(5.0, 1.5)
    feats = onehot_features(labels, 16, 2)
    uv = (250.3, 240.6)
    res = Verifier().verify(candidate(uv, depth, cam, feats))
    rec = res.record
    assert res.accepted and rec.refinement_ran and rec.refinement_note is RefinementNote.SEMANTIC
    assert rec.refined_uv == uv and rec.pixel_shift_px == 0.0
    theta = math.atan((uv[0] - 320.0) / 320.0)
    gate = math.exp(-0.5 * (theta / (0.5 * math.pi / 4)) ** 2)
    assert rec.bearing_rad == pytest.approx(theta, abs=1e-12)
    assert rec.gating_factor == pytest.approx(gate, rel=1e-12)
    expected = 5.0 * gate * np.array([(uv[0] - 320.0) / 320.0, (uv[1] - 240.0) / 320.0, 1.0])
    np.testing.assert_allclose(res.goal_world, expected, rtol=0, atol=1e-12)


def test_edge_pixel_moves_to_nearest_feasible_pixel_of_its_region():
    cam, depth, labels = edge_scene(5.0, 1.5)  # obstacle at 1.5 m for columns >= 336
    labels[:160] = 2  # the wall above and below the target band is another region
    labels[320:] = 2
    feats = onehot_features(labels, 16, 3)
    uv = (335.0, 240.0)  # target pixel on the obstacle's edge
    cfg = VerifierConfig()
    cand = candidate(uv, depth, cam, feats)
    res = Verifier(cfg).verify(cand)
    rec = res.record
    assert res.accepted and rec.refinement_note is RefinementNote.SEMANTIC
    u2, v2 = rec.refined_uv
    assert labels[int(v2), int(u2)] == 0 and v2 == 240.0 and u2 < 336
    # Hand computation: the nearest obstacle point is pixel (336, 240) at 1.5 m; the ray of
    # column c clears it by r when atan(16/320) - atan((c-320)/320) >= asin(r / |Y|).
    Y = np.array([16 / 320 * 1.5, 0.0, 1.5])
    beta = math.asin(R_M / np.linalg.norm(Y))
    c_exact = math.floor(320 + 320 * math.tan(math.atan(16 / 320) - beta))
    assert c_exact == 293
    roi = (192, 288, 287, 383)
    d_exact = exact_nearest_feasible(cam, depth, labels, uv, 0, roi, 4.0)
    assert d_exact == pytest.approx(335 - c_exact)
    # Never closer than the exact answer (it is safe), and at most 15 % + 2 px farther.
    assert d_exact <= rec.pixel_shift_px <= 1.15 * d_exact + 2.0
    assert_safe(res, cand, cfg)
    assert ray_clearance(obstacle_points(cam, depth, 4.0), cam, rec.refined_uv) >= R_M


def test_refinement_never_leaves_the_semantic_region():
    cam, depth, labels = edge_scene(5.0, 1.5)
    labels[:, :336] = 2  # wall: region C ...
    labels[224:256, 304:336] = 0  # ... except a 2 x 2-patch target block touching the obstacle
    feats = onehot_features(labels, 16, 3)
    uv = (334.0, 240.0)
    # Every pixel of the target block is within the obstacle's clearance: semantic mode refuses.
    res = Verifier().verify(candidate(uv, depth, cam, feats))
    assert not res.accepted and res.goal_world is None
    assert res.record.rejection is RejectionReason.NO_FEASIBLE_PIXEL
    assert res.record.refinement_ran and res.record.component_size_px == 32 * 32
    # Geometric-only mode (no features) may move into region C, and says so.
    cand = candidate(uv, depth, cam, None)
    geo = Verifier().verify(cand)
    assert geo.accepted and geo.record.geometric_only and geo.record.refinement_note is RefinementNote.NO_FEATURES
    u2, v2 = geo.record.refined_uv
    assert labels[int(v2), int(u2)] == 2
    assert_safe(geo, cand, VerifierConfig())


def pole_and_box():
    """The issue's case: a pole 1.5 m away (columns 312-327, label 1) in front of a box face at
    3 m (label 0) filling the rest of the square camera's view."""
    cam = square_camera()
    depth = np.full(cam.shape, 3.0, np.float32)
    labels = np.zeros(cam.shape, dtype=int)
    depth[:, 312:328] = 1.5
    labels[:, 312:328] = 1
    return cam, depth, labels


@pytest.mark.parametrize("with_features", [False, True])
def test_pole_and_box_keeps_the_goal_on_the_pole(with_features):
    cam, depth, labels = pole_and_box()
    feats = onehot_features(labels, 16, 2) if with_features else None
    uv = (320.0, 240.0)
    cand = candidate(uv, depth, cam, feats)
    res = Verifier().verify(cand)
    rec = res.record
    # The pole is the target's own surface: the near-field rule does not push the goal onto the
    # box behind it (the old geometric search gave pixel (192, 107) at 3.0 m, note no_features).
    assert res.accepted and rec.refined_uv == uv and rec.refined_depth_m == 1.5
    assert rec.geometric_only is (not with_features)
    assert rec.obstacle_threshold_m == 2.0
    # On the pole's ray, r in front of the pole (the clear part of the ray): 1.5 - 0.2 m.
    assert rec.clear_range_m == pytest.approx(1.3, abs=1e-5)
    np.testing.assert_allclose(res.goal_world, [0.0, 0.0, 1.3], atol=1e-5)
    assert_safe(res, cand, VerifierConfig())


def test_pole_and_box_target_on_the_box_stays_on_the_box_without_features():
    cam, depth, labels = pole_and_box()
    uv = (332.0, 240.0)  # on the box, 4 px right of the pole: its ray grazes the pole
    cand = candidate(uv, depth, cam, None)
    res = Verifier().verify(cand)
    rec = res.record
    assert res.accepted and rec.geometric_only and rec.refinement_note is RefinementNote.NO_FEATURES
    u2, v2 = rec.refined_uv
    assert labels[int(v2), int(u2)] == 0 and u2 > 328 and rec.refined_depth_m == 3.0
    # The component is the box surface right of the pole only (the pole splits the ROI).
    assert rec.component_size_px == 128 * (396 - 328)
    assert_safe(res, cand, VerifierConfig())


def test_surface_region_is_bounded_by_depth_edges_and_the_band():
    cam, depth, _ = pole_and_box()
    from planning.verifier import surface_region

    pole = surface_region(depth, 240, 320, 0.1, 1.0)
    assert pole.sum() == 480 * 16 and pole[:, 312:328].all()
    # A slanted surface (depth growing 2 % per column) is one surface; a 15 % step splits it.
    ramp = np.tile((3.0 * 1.02 ** np.arange(64)).astype(np.float32), (8, 1))
    ramp[:, 40:] *= 1.15
    region = surface_region(ramp, 4, 0, 0.1, math.inf)
    assert region[:, :40].all() and not region[:, 40:].any()
    # The band stops a continuous surface 1 m beyond the seed's depth.
    region = surface_region(ramp, 4, 0, 0.1, 1.0)
    assert region.any(axis=0).sum() == int(np.sum(np.abs(ramp[0, :40] - 3.0) <= 1.0))
    with pytest.raises(ValueError, match="no reading"):
        surface_region(np.zeros((4, 4), np.float32), 1, 1, 0.1, 1.0)


def test_obstacle_rule_is_evaluated_at_the_refined_pixel():
    """The target's semantic region has a 3 m part (where the VLM pointed, next to an obstacle
    at 1.5 m) and a 6 m part; a post at 4.5 m is no obstacle for a goal at 3 m (T = 2 m) but is
    one for a goal at 6 m (T = 5 m). The nearest pixel clearing the 1.5 m obstacle lies on the 6 m
    part right beside the post: the rule at the refined pixel must reject it."""
    cam = square_camera()
    depth = np.full(cam.shape, 6.0, np.float32)
    labels = np.zeros(cam.shape, dtype=int)
    depth[:, 300:336] = 3.0
    depth[:, 336:] = 1.5
    labels[:, 336:] = 1
    depth[200:280, 286:292] = 4.5
    labels[200:280, 286:292] = 2
    feats = onehot_features(labels, 2, 3)
    uv = (334.0, 240.0)
    cand = candidate(uv, depth, cam, feats, patch=2.0)
    res = Verifier().verify(cand)
    post = obstacle_points(cam, np.where(labels == 2, depth, np.nan).astype(np.float32), np.inf)
    # The target's own rule alone would accept (293, 240), 0.02 m from the post's ray.
    assert ray_clearance(post, cam, (293.0, 240.0)) < R_M
    assert res.accepted
    rec = res.record
    u2, v2 = rec.refined_uv
    assert rec.refined_depth_m == 6.0 and rec.obstacle_threshold_m == 5.0
    assert ray_clearance(post, cam, rec.refined_uv) >= R_M
    assert_safe(res, cand, VerifierConfig())


@pytest.mark.parametrize("connectivity, accepted", [(4, False), (8, True)])
def test_regions_touching_at_a_corner_join_only_with_8_connectivity(connectivity, accepted):
    cam, depth, labels = edge_scene(5.0, 1.5)
    labels[:, :336] = 2
    labels[224:256, 304:336] = 0  # target block, all within the obstacle clearance ...
    labels[192:224, 272:304] = 0  # ... touching another target block only at a corner
    feats = onehot_features(labels, 16, 3)
    res = Verifier(VerifierConfig(connectivity=connectivity)).verify(candidate((334.0, 240.0), depth, cam, feats))
    assert res.accepted is accepted
    if accepted:
        u2, v2 = res.record.refined_uv
        assert labels[int(v2), int(u2)] == 0 and v2 < 224


def test_dilation_scales_with_depth():
    shifts, clearances = {}, {}
    for z_obstacle, z_target, margin in ((2.0, 4.0, 1.0), (6.0, 7.0, 0.5)):
        cam, depth, labels = edge_scene(z_target, z_obstacle)
        cfg = VerifierConfig(foreground_margin_m=margin)
        cand = candidate((335.0, 240.0), depth, cam, onehot_features(labels, 16, 2))
        res = Verifier(cfg).verify(cand)
        assert res.accepted and res.record.refined_uv[1] == 240.0
        P = obstacle_points(cam, depth, rule_threshold(cfg, depth, cand.pixel_uv))
        assert len(P) == 480 * 304  # the whole obstacle counts at both depths
        shifts[z_obstacle] = res.record.pixel_shift_px
        clearances[z_obstacle] = ray_clearance(P, cam, res.record.refined_uv)
        assert_safe(res, cand, cfg)
    # The same metric clearance (r, up to binning and one pixel at 6 m) ...
    for z, c in clearances.items():
        assert R_M <= c <= 1.3 * R_M, (z, c)
    # ... is three times as many pixels at a third of the depth.
    assert 2.6 <= shifts[2.0] / shifts[6.0] <= 3.4


def test_cone_radius_matches_small_angle_rule_on_axis_and_grows_off_axis():
    f, r = 320.0, 0.2
    for z in (1.0, 2.0, 6.0):
        assert cone_radius_px(0.0, z, r, f) == pytest.approx(f * r / math.sqrt(z * z - r * r), rel=1e-12)
    # Off axis the disc is wider: tan(psi + beta) - tan(psi) at the 45 deg image edge.
    psi, rho = math.pi / 4, 3.0
    beta = math.asin(r / rho)
    assert cone_radius_px(1.0, rho, r, f) == pytest.approx(f * (math.tan(psi + beta) - 1.0), rel=1e-12)
    assert cone_radius_px(0.0, 0.1, r, f) == math.inf  # camera inside the clearance ball


# -- skipped refinement ------------------------------------------------------------------------


def test_beyond_d_max_skips_refinement_and_clamps_the_range():
    cam, depth, labels = edge_scene(10.0, 10.0)
    uv = (300.0, 250.0)
    res = Verifier().verify(candidate(uv, depth, cam, onehot_features(labels, 16, 2)))
    rec = res.record
    assert res.accepted and not rec.refinement_ran and rec.refinement_note is RefinementNote.BEYOND_D_MAX
    assert rec.refined_uv == uv and rec.target_depth_m == 10.0 and rec.refined_depth_m == 7.0
    assert rec.component_size_px == 0
    np.testing.assert_allclose(res.goal_world, cam.back_project(np.array(uv), 7.0 * rec.gating_factor), atol=1e-12)


def test_beyond_d_max_next_to_a_foreground_obstacle_is_kept_with_the_range_gated_by_hand():
    cam, depth, labels = edge_scene(10.0, 3.0)  # obstacle at 3 m for columns >= 336
    uv = (330.0, 240.0)
    cand = candidate(uv, depth, cam, onehot_features(labels, 16, 2))
    res = Verifier().verify(cand)
    rec = res.record
    # Kept per the paper (p' = p) ...
    assert res.accepted and rec.refined_uv == uv and rec.refinement_note is RefinementNote.BEYOND_D_MAX
    # ... with the range cut where the ray first comes within r of a reading. By hand: the ray
    # through column 330 has unit direction dvec; the nearest obstacle points are column 336 at
    # 3 m (rows around 240); the ray enters the ball of radius r around Y at a - sqrt(r^2 - q^2).
    dvec = np.array([10.0 / 320.0, 0.0, 1.0])
    dvec /= np.linalg.norm(dvec)
    Y = np.array([16.0 / 320.0 * 3.0, 0.0, 3.0])
    a = float(Y @ dvec)
    q2 = float(Y @ Y - a * a)
    z_clear = (a - math.sqrt(R_M * R_M - q2)) * dvec[2]
    assert 2.79 < z_clear < 2.83
    assert rec.clear_range_m == pytest.approx(z_clear, abs=1e-5)
    assert rec.range_m == pytest.approx(min(7.0 * rec.gating_factor, rec.clear_range_m), abs=1e-12)
    assert_safe(res, cand, VerifierConfig())
    # A ray that hits a reading right in front of the camera leaves no useful goal.
    depth[230:250, 332:340] = 0.4  # beside the target pixel, which keeps its 10 m reading
    res = Verifier().verify(candidate(uv, depth, cam))
    assert not res.accepted and res.record.rejection is RejectionReason.UNREFINED_TARGET_UNSAFE
    assert res.record.clear_range_m < 0.5


# -- step 2: gating and the world transform -------------------------------------------------------


def test_bearing_gate_hand_values():
    tmax = math.pi / 4
    assert bearing_gate(0.0, tmax, 0.5) == 1.0
    assert bearing_gate(tmax, tmax, 0.5) == pytest.approx(math.exp(-2.0), rel=1e-14)
    assert bearing_gate(-1.5 * tmax, tmax, 0.5) == pytest.approx(math.exp(-4.5), rel=1e-14)
    # Half range at 1.177 sigma theta_max (the documented choice).
    assert bearing_gate(math.sqrt(2 * math.log(2)) * 0.5 * tmax, tmax, 0.5) == pytest.approx(0.5, rel=1e-12)
    np.testing.assert_allclose(bearing_gate(np.array([0.0, tmax]), tmax, 1.0), [1.0, math.exp(-0.5)])


@pytest.mark.parametrize("cx", [320.0, 200.0])
def test_gating_in_the_verifier_at_centre_and_edge(cx):
    # cx = 200 puts the right image edge beyond theta_max = hfov / 2 (hfov assumes a centred cx).
    cam = PinholeCamera(640, 480, 320.0, 320.0, cx, 240.0)
    depth = np.full(cam.shape, 5.0, np.float32)
    ver = Verifier()
    theta_max = 0.5 * cam.hfov_rad
    for u in (cx, 639.0):
        res = ver.verify(candidate((u, 240.0), depth, cam))
        rec = res.record
        theta = math.atan((u - cx) / 320.0)
        gate = math.exp(-0.5 * (theta / (0.5 * theta_max)) ** 2)
        assert rec.bearing_rad == pytest.approx(theta, abs=1e-12)
        assert rec.gating_factor == pytest.approx(gate, rel=1e-12)
        assert rec.range_m == pytest.approx(5.0 * gate, rel=1e-12)
        np.testing.assert_allclose(res.goal_world, 5.0 * gate * np.array([(u - cx) / 320.0, 0.0, 1.0]), atol=1e-12)
    if cx == 200.0:
        assert math.atan(439.0 / 320.0) > theta_max and rec.gating_factor < math.exp(-2.0)


def test_goal_round_trips_through_camera_model_and_pose():
    rng = np.random.default_rng(3)
    cam = PinholeCamera.from_fov(640, 480, 90, 60)
    depth = rng.uniform(3.0, 6.0, size=(1, 1)).astype(np.float32) * np.ones(cam.shape, np.float32)
    for _ in range(20):
        T_world_body = body_transform(rng.uniform(-5, 5, 3), rng.uniform(-math.pi, math.pi), 0.1, -0.05)
        T = cam_transform_from_body(T_world_body)
        uv = (rng.uniform(0, 639), rng.uniform(0, 479))
        res = Verifier().verify(candidate(uv, depth, cam, T=T))
        assert res.accepted
        X_cam = transform_points(invert_transform(T), res.goal_world)
        uv_back, in_front = cam.project(X_cam)
        assert in_front
        np.testing.assert_allclose(uv_back, res.record.refined_uv, atol=1e-9)
        assert X_cam[2] == pytest.approx(res.record.range_m, abs=1e-12)
        np.testing.assert_allclose(
            res.goal_world, transform_points(T, cam.back_project(np.array(uv), res.record.range_m)), atol=1e-12
        )


# -- bad input: documented rejections, never a goal in an obstacle ------------------------------


@pytest.mark.parametrize("hole", [np.nan, 0.0, np.inf])
@pytest.mark.parametrize("with_features", [False, True])
def test_hole_in_the_wall_gives_no_goal_behind_the_wall(hole, with_features):
    """Issue 17: a wall at 5 m with a 40 x 40 px patch of no readings (glass, a dark surface);
    the VLM points into the patch. The default config never treats the patch as open space."""
    cam = square_camera()
    depth = np.full(cam.shape, 5.0, np.float32)
    depth[220:260, 300:340] = hole
    feats = np.ones((30, 40, 4)) if with_features else None
    uv = (320.0, 240.0)
    cand = candidate(uv, depth, cam, feats)
    res = Verifier().verify(cand)
    rec = res.record
    assert res.accepted and rec.refinement_note is RefinementNote.NO_DEPTH_READING and not rec.refinement_ran
    assert rec.bound_depth_m == 5.0 and rec.refined_uv == uv
    # The goal stays r in front of the wall's plane: on axis, exactly 5 - 0.2 m.
    assert rec.clear_range_m == pytest.approx(4.8, abs=1e-5)  # (a micron short of the ball)
    np.testing.assert_allclose(res.goal_world, [0.0, 0.0, 4.8], atol=1e-5)
    assert_safe(res, cand, VerifierConfig())
    for u in np.linspace(300.0, 339.0, 7):  # anywhere in the patch
        r = Verifier().verify(candidate((float(u), 230.0), depth, cam, feats))
        assert r.accepted and r.goal_world[2] < 5.0 - 0.19
    strict = Verifier(VerifierConfig(reject_no_reading=True)).verify(cand)
    assert not strict.accepted and strict.record.rejection is RejectionReason.NO_DEPTH_AT_TARGET


@pytest.mark.parametrize("hole", [np.nan, 0.0])
def test_no_reading_next_to_a_near_obstacle_is_bounded_by_it(hole):
    cam, depth, labels = edge_scene(5.0, 1.5)
    depth[230:250, 325:336] = hole  # the hole borders the wall (5 m) and the obstacle (1.5 m)
    cand = candidate((330.0, 240.0), depth, cam, onehot_features(labels, 16, 2))
    res = Verifier().verify(cand)
    rec = res.record
    assert rec.bound_depth_m == 1.5
    assert res.accepted and res.goal_world[2] < 1.5 - 0.19
    assert_safe(res, cand, VerifierConfig())


def test_no_reading_anywhere_near_the_target_is_rejected():
    cam = square_camera()
    depth = np.full(cam.shape, 5.0, np.float32)
    depth[100:400, 100:500] = np.nan  # a hole larger than the 128 px ROI around the target
    res = Verifier().verify(candidate((320.0, 240.0), depth, cam))
    assert not res.accepted and res.record.rejection is RejectionReason.NO_DEPTH_AT_TARGET
    assert res.record.refinement_note is RefinementNote.NO_DEPTH_READING


@pytest.mark.parametrize("fill", [np.nan, 0.0, np.inf, -1.0])
def test_all_invalid_depth_is_rejected(fill):
    cam = square_camera()
    depth = np.full(cam.shape, fill, np.float32)
    res = Verifier().verify(candidate((320.0, 240.0), depth, cam))
    assert not res.accepted and res.record.rejection is RejectionReason.INVALID_DEPTH_EVERYWHERE


@pytest.mark.parametrize("uv", [(-0.6, 10.0), (639.5, 10.0), (10.0, 479.5), (float("nan"), 3.0), (1e9, -1e9)])
def test_pixel_outside_the_image_is_rejected(uv):
    cam, depth, _ = edge_scene(5.0, 1.5)
    res = Verifier().verify(candidate(uv, depth, cam))
    assert not res.accepted and res.record.rejection is RejectionReason.PIXEL_OUTSIDE_IMAGE
    assert res.record.refinement_note is RefinementNote.NOT_ATTEMPTED


def test_degenerate_feature_at_target_falls_back_to_geometric_only():
    cam, depth, labels = edge_scene(5.0, 1.5)
    feats = onehot_features(labels, 16, 2)
    feats[15, 20] = 0.0  # the patch containing the target
    feats[10, 10] = np.nan  # a non-finite patch elsewhere is simply not similar
    res = Verifier().verify(candidate((330.0, 245.0), depth, cam, feats))
    assert res.accepted and res.record.geometric_only
    assert res.record.refinement_note is RefinementNote.DEGENERATE_FEATURE


def test_camera_inside_the_clearance_of_an_obstacle_rejects_everything():
    cam, depth, labels = edge_scene(5.0, 1.5)
    depth[0, 0] = 0.1  # an obstacle point 0.1 m from the camera: no ray clears it by 0.2 m
    for uv in ((100.0, 100.0), (500.0, 400.0)):
        res = Verifier().verify(candidate(uv, depth, cam, onehot_features(labels, 16, 2)))
        assert not res.accepted and res.record.rejection is RejectionReason.NO_FEASIBLE_PIXEL


def test_verify_is_deterministic_and_does_not_modify_inputs():
    cam, depth, labels = edge_scene(5.0, 1.5)
    feats = onehot_features(labels, 16, 2)
    depth_copy, feats_copy = depth.copy(), feats.copy()
    cand = candidate((335.0, 240.0), depth, cam, feats)
    a, b = Verifier().verify(cand), Verifier().verify(cand)
    assert a.record == b.record
    np.testing.assert_array_equal(a.goal_world, b.goal_world)
    np.testing.assert_array_equal(depth, depth_copy)
    np.testing.assert_array_equal(feats, feats_copy)


# -- property: random box scenes -----------------------------------------------------------------


def random_scene(rng, cam):
    """Ground, an optional back wall (sky above it has no reading) and 2-6 boxes on the ground."""
    h_cam = rng.uniform(0.8, 2.0)
    boxes = [((-60.0, h_cam, 0.0), (60.0, h_cam + 1.0, 80.0))]
    if rng.random() < 0.8:
        z_wall = rng.uniform(4.0, 14.0)
        boxes.append(((-60.0, h_cam - rng.uniform(2.0, 8.0), z_wall), (60.0, h_cam, z_wall + 1.0)))
    for _ in range(rng.integers(2, 7)):
        z = rng.uniform(0.6, 9.0)
        x = rng.uniform(-4.0, 4.0)
        w, d, hgt = rng.uniform(0.1, 2.0), rng.uniform(0.1, 2.0), rng.uniform(0.3, 3.0)
        boxes.append(((x - w / 2, h_cam - hgt, z), (x + w / 2, h_cam, z + d)))
    return render_boxes(cam, boxes, no_hit=rng.choice([np.nan, 0.0]))


def random_candidates(rng, labels, n_random=2, n_edges=3):
    """Uniform pixels plus pixels near label edges (where refinement matters)."""
    h, w = labels.shape
    out = [(rng.uniform(-0.5, w - 0.5), rng.uniform(-0.5, h - 0.5)) for _ in range(n_random)]
    edges = np.argwhere((labels[:, 1:] != labels[:, :-1]))
    for k in rng.choice(len(edges), size=min(n_edges, len(edges)), replace=False):
        r, c = edges[k]
        out.append((float(np.clip(c + rng.normal(0, 2.0), 0, w - 1)), float(np.clip(r + rng.normal(0, 2.0), 0, h - 1))))
    return out


def test_property_goal_clears_every_visible_obstacle_by_r():
    rng = np.random.default_rng(20260525)
    cams = [PinholeCamera.from_fov(160, 120, 90, 60), PinholeCamera(160, 120, 90.0, 90.0, 79.5, 59.5)]
    configs = [
        VerifierConfig(roi_px=32),
        VerifierConfig(roi_px=48, obstacle_depth_m=3.0, foreground_margin_m=0.5, tau=0.3),
        VerifierConfig(roi_px=24, clearance_radius_m=0.35, connectivity=8, radius_class_ratio=1.5),
    ]
    stats = {"accepted": 0, "moved": 0, "rejected": 0, "skipped": 0}
    for scene in range(150):
        cam = cams[scene % 2]
        depth, labels = random_scene(rng, cam)
        feats = random_label_features(labels, 8, 12, seed=scene) if scene % 3 else None
        T = cam_transform_from_body(body_transform(rng.uniform(-3, 3, 3), rng.uniform(-3, 3)))
        cfg = configs[scene % 3]
        ver = Verifier(cfg)
        for uv in random_candidates(rng, labels):
            cand = CandidateGoal(uv, depth, feats, 8.0, T, cam)
            res = ver.verify(cand)
            if not res.accepted:
                stats["rejected"] += 1
                continue
            stats["accepted"] += 1
            stats["moved"] += res.record.pixel_shift_px > 0
            stats["skipped"] += not res.record.refinement_ran
            assert_safe(res, cand, cfg)
            X_cam = transform_points(invert_transform(T), res.goal_world)
            if res.record.refinement_ran:  # the whole ray clears the rule at the refined pixel
                P = rule_obstacles(cfg, depth, uv, res.record.refined_uv, cam)
                assert ray_clearance(P, cam, res.record.refined_uv) >= cfg.clearance_radius_m - 1e-9
            assert X_cam[2] <= cfg.d_max_m + 1e-9
    # The property is not vacuous: many goals accepted, many of them moved or unrefined.
    assert stats["accepted"] >= 300 and stats["moved"] >= 60 and stats["skipped"] >= 30 and stats["rejected"] >= 30, stats


# -- real depth ---------------------------------------------------------------------------------


def test_property_on_real_kinect_depth():
    frames = sorted((KITCHEN / "depth").glob("*.png"))
    assert len(frames) >= 30
    cam = PinholeCamera(640, 480, 585.0, 585.0, 320.0, 240.0)
    rng = np.random.default_rng(7)
    cfg = VerifierConfig()
    ver = Verifier(cfg)
    accepted = 0
    for path in frames[::15]:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert raw is not None and raw.dtype == np.uint16
        depth = raw.astype(np.float32) / 5000.0  # 0 stays "no reading"
        assert 0.05 < np.mean(depth == 0) < 0.6 or np.any(depth == 0)
        # Features: 16 px patches labelled by quantized median depth (a stand-in for semantics).
        patch_depth = np.median(depth.reshape(30, 16, 40, 16), axis=(1, 3))
        feats = np.eye(8)[np.clip((patch_depth / 0.5).astype(int), 0, 7)]
        for k in range(12):
            uv = (rng.uniform(0, 639), rng.uniform(0, 479))
            cand = CandidateGoal(uv, depth, feats if k % 2 else None, 16.0, np.eye(4), cam)
            res = ver.verify(cand)
            if res.accepted:
                accepted += 1
                assert_safe(res, cand, cfg)
    assert accepted >= 10
