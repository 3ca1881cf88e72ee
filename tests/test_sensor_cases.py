"""Constructed sensor cases: depth frames and poses as bad as a real RGB-D camera and odometry
give them, pushed through every entry point that reads them (docs/robustness.md,
"Constructed sensor cases").

Entry points: ``Observation``, ``EsdfMap.integrate``, the verifier's ``CandidateGoal`` /
``Verifier.verify``, the pilot's per-frame step, the TUM reader and ``onfly replay`` on a small
constructed recording, and the camera channel's wire format. The rule asserted everywhere: a
clear error at the boundary naming what is wrong, or a documented safe action (the pixel has
no reading, the frame is skipped and counted, the vehicle holds); never free space where
nothing was read, never a goal through or behind a surface, never a unit mistake that flies.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from onfly.cli import main
from onfly.mavlink.camera_channel import FrameChannelError, decode_observation, encode_observation
from onfly.observation import Observation
from onfly.pilot import OnFlyPilot, PilotConfig, PilotMode
from onfly.readers.tum import TumFormatError, TumReader
from onfly.replay import ReplayConfig, replay
from onfly.runtime import ClockRuntime
from planning.camera import DEPTH_IMPLAUSIBLE_M, CameraError, PinholeCamera, depth_from_counts
from planning.esdf import EsdfError, EsdfMap
from planning.esdf_config import EsdfConfig
from planning.frames import FrameError, T_BODY_CAM, body_transform, transform_points
from planning.verifier import CandidateGoal, Verifier, VerifierConfig, VerifierInputError
from test_verifier import assert_safe  # the verifier suite's brute-force safety check
from vlm_fakes import ScriptedVlm

CAM = PinholeCamera(64, 48, 32.0, 32.0, 31.5, 23.5)  # 90 x 73 deg, small enough to be quick
T_ID = np.eye(4)  # camera optical frame = world: z forward (the verifier's goals read in the camera frame)
T_LEVEL = body_transform([0.0, 0.0, 1.5], 0.0) @ T_BODY_CAM  # a level camera 1.5 m up looking east (the map)
WALL_M = 3.0
R_M = VerifierConfig().clearance_radius_m
NO_READING = [0.0, np.nan, np.inf, -np.inf, -1.0]
FAST = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def wall(depth_m: float = WALL_M, cam: PinholeCamera = CAM) -> np.ndarray:
    return np.full(cam.shape, depth_m, np.float32)


def obs_of(depth, cam: PinholeCamera = CAM, T=T_ID, t_s: float = 0.0, rgb=None, frame_id: str = "f") -> Observation:
    rgb = np.zeros((*cam.shape, 3), np.uint8) if rgb is None else rgb
    return Observation(t_s=t_s, rgb=rgb, depth_m=depth, T_world_cam=T, camera=cam, frame_id=frame_id)


def reading_points(cam: PinholeCamera, depth: np.ndarray) -> np.ndarray:
    P, _ = cam.depth_to_points(depth)
    return P


def segment_clearance(P: np.ndarray, goal_cam: np.ndarray) -> float:
    """Smallest distance from the points P (n, 3) to the segment camera -> goal (optical frame)."""
    g = np.asarray(goal_cam, float)
    s = np.clip(P @ g / max(g @ g, 1e-12), 0.0, 1.0)
    return float(np.min(np.linalg.norm(P - s[:, None] * g, axis=1))) if len(P) else np.inf


# -- Observation: the boundary ---------------------------------------------------------------------


@pytest.mark.parametrize("bad", NO_READING + [0.01])
def test_no_reading_values_are_kept_and_never_become_points(bad):
    """0 / NaN / +-inf / negative are no reading (README "Conventions"); the observation keeps
    them as they are and back-projection drops them (no point at the origin, at infinity or
    behind the camera). 0.01 m is a reading the map drops later (``min_range_m``)."""
    d = wall()
    d[10:20, 10:30] = bad
    o = obs_of(d)
    assert o.depth_m.dtype == np.float32
    np.testing.assert_array_equal(o.depth_m[10:20, 10:30], np.float32(bad))
    P = reading_points(CAM, o.depth_m)
    n_hole = 0 if bad == 0.01 else 200
    assert len(P) == CAM.width * CAM.height - n_hole
    assert np.all(np.isfinite(P)) and np.all(P[:, 2] > 0)


@pytest.mark.parametrize("dtype", [np.uint16, np.int32, np.uint8, np.int64])
def test_an_integer_depth_frame_is_refused_with_the_conversion_to_use(dtype):
    """A uint16 frame in millimetres was cast to float and read as metres: a wall at 1.5 m read
    1500 m, beyond range, and cleared free space through the wall. Now every entry point refuses
    it, naming the dtype and the conversion."""
    mm = np.full(CAM.shape, 150, dtype)
    with pytest.raises(CameraError, match=f"depth_m is {np.dtype(dtype).name}: raw sensor counts.*depth_from_counts"):
        obs_of(mm)
    with pytest.raises(EsdfError, match="raw sensor counts"):
        EsdfMap(EsdfConfig()).integrate(mm, CAM, T_ID)
    with pytest.raises(VerifierInputError, match="raw sensor counts"):
        CandidateGoal((32.0, 24.0), mm, None, 16.0, T_ID, CAM)


@pytest.mark.parametrize("what", ["bool", "str", "complex"])
def test_a_depth_frame_of_another_kind_is_refused(what):
    arr = {"bool": np.ones(CAM.shape, bool), "str": np.full(CAM.shape, "x"), "complex": np.ones(CAM.shape, complex)}[what]
    with pytest.raises(CameraError, match="depth_m"):
        obs_of(arr)


def test_a_float_frame_in_millimetres_is_refused_and_far_readings_are_kept():
    """A float frame in millimetres (REP 118: 32FC1 is metres) has every reading 1000 times too
    far. Refused when most readings lie beyond 65.535 m (no 16-bit mm image says more, no
    RGB-D camera here reads that far); a few far or garbage readings (1e6 m) are readings
    beyond the map's range and kept."""
    mm = np.random.default_rng(0).uniform(400.0, 5000.0, CAM.shape).astype(np.float32)
    mm[:5] = 0.0  # with holes
    for entry in (lambda: obs_of(mm), lambda: EsdfMap(EsdfConfig()).integrate(mm, CAM, T_ID),
                  lambda: CandidateGoal((32.0, 24.0), mm, None, 16.0, T_ID, CAM)):  # fmt: skip
        with pytest.raises(ValueError, match="was it given in millimetres"):
            entry()
    d = wall()
    d[:10] = 1e6
    d[10:12] = DEPTH_IMPLAUSIBLE_M * 2
    assert obs_of(d).depth_m[0, 0] == np.float32(1e6)
    # the reverse: metres where counts are expected is refused by the conversion
    with pytest.raises(CameraError, match="integer array"):
        depth_from_counts(wall(), 1000.0)


def test_sixteen_bit_counts_convert_with_zero_and_saturation_as_no_reading():
    """TUM (5000 / m), REP 118 / RealSense (1000 / m): 0 is no reading; 65535, the encoding's
    ceiling, is saturated, no reading (never a 65 m reading that clears its ray)."""
    counts = np.array([[0, 1, 1500, 65534, 65535]], np.uint16)
    np.testing.assert_allclose(depth_from_counts(counts, 1000.0), [[0.0, 0.001, 1.5, 65.534, 0.0]], rtol=1e-6)
    np.testing.assert_allclose(depth_from_counts(counts, 5000.0), [[0.0, 0.0002, 0.3, 13.1068, 0.0]], rtol=1e-6)
    np.testing.assert_allclose(depth_from_counts(np.array([[-5, 700]], np.int32), 1000.0), [[0.0, 0.7]], rtol=1e-6)
    with pytest.raises(CameraError, match="per metre"):
        depth_from_counts(counts, 0.0)


@pytest.mark.parametrize(
    "depth_shape, rgb_shape, match",
    [
        ((48, 63), (48, 64, 3), r"depth_m must have shape \(48, 64"),
        ((47, 64), (48, 64, 3), r"depth_m must have shape \(48, 64"),
        ((48, 64), (48, 63, 3), r"rgb must have shape \(48, 64"),
        ((64, 48), (48, 64, 3), r"depth_m must have shape \(48, 64"),  # transposed
        ((48, 64, 1), (48, 64, 3), r"depth_m must be a 2-D"),
        ((48, 64), (48, 64), "rgb must be uint8 \\(H, W, 3\\)"),
    ],
)
def test_a_frame_whose_shape_differs_from_the_intrinsics_or_the_rgb_is_refused(depth_shape, rgb_shape, match):
    with pytest.raises(CameraError if "shape (48" in match or "2-D" in match else ValueError, match=match):
        obs_of(np.full(depth_shape, 2.0, np.float32), rgb=np.zeros(rgb_shape, np.uint8))
    if len(depth_shape) == 2 and depth_shape != CAM.shape:
        with pytest.raises(CameraError, match="depth_m must have shape"):
            EsdfMap(EsdfConfig()).integrate(np.full(depth_shape, 2.0, np.float32), CAM, T_ID)
        with pytest.raises(VerifierInputError, match="depth_m must have shape"):
            CandidateGoal((1.0, 1.0), np.full(depth_shape, 2.0, np.float32), None, 16.0, T_ID, CAM)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(fx=0.0), "focal lengths must be positive"),
        (dict(fy=-32.0), "focal lengths must be positive"),
        (dict(fx=np.nan), "finite"),
        (dict(cx=64.0), r"principal point \(64.0, 23.5\) lies outside the 64 x 48 image"),
        (dict(cy=-1.0), "principal point"),
        (dict(cx=319.5, cy=239.5), "intrinsics of another resolution"),  # a 640 x 480 calibration
    ],
)
def test_intrinsics_with_a_bad_focal_length_or_principal_point_are_refused(kw, match):
    args = dict(width=64, height=48, fx=32.0, fy=32.0, cx=31.5, cy=23.5) | kw
    with pytest.raises(CameraError, match=match):
        PinholeCamera(**args)
    # the edges of the image are still a valid principal point
    PinholeCamera(64, 48, 32.0, 32.0, -0.5, 47.5)


@pytest.mark.parametrize(
    "T, match",
    [
        (np.where(np.eye(4) == 1, np.nan, 0.0), "non-finite"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),  # a mirrored camera
        (np.diag([1.0, 1.0, 1.2, 1.0]), "not orthonormal"),  # a scaled rotation
        (np.array([[1, 0.1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "not orthonormal"),  # sheared
        (np.vstack([np.eye(4)[:3], [0, 0, 1, 1.0]]), "last row"),
        (np.eye(3), r"shape \(4, 4\)"),
    ],
)
def test_a_bad_pose_is_refused_at_every_entry_point(T, match):
    with pytest.raises(FrameError, match=match):
        obs_of(wall(), T=T)
    with pytest.raises(FrameError, match=match):
        EsdfMap(EsdfConfig()).integrate(wall(), CAM, T)
    with pytest.raises(VerifierInputError, match=match):
        CandidateGoal((32.0, 24.0), wall(), None, 16.0, T, CAM)


@pytest.mark.parametrize("t", [np.nan, np.inf, -np.inf])
def test_a_non_finite_timestamp_is_refused(t):
    with pytest.raises(ValueError, match="t_s must be finite"):
        obs_of(wall(), t_s=t)


# -- the map: never free space where nothing was read ----------------------------------------------


def _in_front_points(cam: PinholeCamera, z_m: float, T=T_LEVEL) -> np.ndarray:
    """World points at z-depth ``z_m`` on every 4th pixel's ray of the camera at ``T``, kept
    within the map's 5 m tall window (1.5 m below the camera to 2.4 m above)."""
    uv = np.stack(np.meshgrid(np.arange(0, cam.width, 4.0), np.arange(0, cam.height, 4.0)), -1).reshape(-1, 2)
    P = transform_points(T, cam.back_project(uv, np.full(len(uv), z_m)))
    return P[(P[:, 2] > 0.1) & (P[:, 2] < 3.9)]


@FAST
@given(
    bad=st.sampled_from(NO_READING),
    rect=st.tuples(st.integers(0, 47), st.integers(0, 47), st.integers(0, 63), st.integers(0, 63)),
    wall_m=st.floats(1.5, 6.0),
)
def test_holes_in_a_wall_never_clear_the_space_behind_it(bad, rect, wall_m):
    """A wall with a patch of no readings of any kind: nothing on or behind the wall becomes
    free (the hole is bounded by the wall's own readings, ``docs/esdf_unknown_space.md``)."""
    r0, r1, c0, c1 = sorted(rect[:2]) + sorted(rect[2:])
    d = wall(wall_m)
    d[r0 : r1 + 1, c0 : c1 + 1] = bad
    esdf = EsdfMap(EsdfConfig())
    up = esdf.integrate(d, CAM, T_LEVEL)
    assert up.n_points > 0
    behind = _in_front_points(CAM, wall_m + 0.3)
    assert not esdf.is_free(behind).any()
    assert not esdf.observed_free(_in_front_points(CAM, wall_m)).any()
    # a reading still clears the space in front of it
    assert esdf.observed_free(_in_front_points(CAM, 0.5 * wall_m)).mean() > 0.5


@pytest.mark.parametrize("bad", NO_READING)
def test_an_all_invalid_frame_clears_nothing_the_camera_looks_at(bad):
    esdf = EsdfMap(EsdfConfig())
    up = esdf.integrate(np.full(CAM.shape, bad, np.float32), CAM, T_LEVEL)
    assert up.n_points == 0 and up.n_hit_voxels == 0 and up.n_miss_voxels == 0
    for z in (1.5, 3.0, 6.0):  # beyond the 1.2 m body sphere, which never clears what the camera sees
        assert not esdf.known(_in_front_points(CAM, z)).any()


def test_readings_beyond_range_clear_at_most_max_range_and_mark_no_obstacle():
    """1e6 m (garbage or sky) and a 65 m float reading: beyond ``max_range_m`` (7 m) they mark
    no obstacle and clear their ray up to 7 m, as the map documents; never past it."""
    cfg = EsdfConfig()
    d = np.full(CAM.shape, 1e6, np.float32)
    d[:, :32] = 65.0
    esdf = EsdfMap(cfg)
    esdf.integrate(d, CAM, T_LEVEL)
    assert esdf.occupied_points().size == 0
    assert esdf.observed_free(_in_front_points(CAM, cfg.max_range_m - 0.5)).all()
    assert not esdf.known(_in_front_points(CAM, cfg.max_range_m + 0.3)).any()


@pytest.mark.parametrize("shape", [(1, 64), (48, 1), (1, 1)])
def test_a_single_row_or_column_frame_flows_through_map_and_verifier(shape):
    h, w = shape
    cam = PinholeCamera(w, h, 32.0, 32.0, (w - 1) / 2, (h - 1) / 2)
    d = wall(3.0, cam)
    if h * w > 1:
        d.flat[0] = np.nan
    o = obs_of(d, cam=cam)
    esdf = EsdfMap(EsdfConfig())
    up = esdf.integrate(o.depth_m, cam, T_LEVEL)
    assert 0 < up.n_points <= max(h * w - 1, 1)  # the NaN pixel is dropped
    assert not esdf.is_free(transform_points(T_LEVEL, np.array([[0.0, 0.0, 3.3]]))).any()
    cand = CandidateGoal(((w - 1) / 2, (h - 1) / 2), d, None, 16.0, T_ID, cam)
    res = Verifier().verify(cand)
    assert res.accepted and res.goal_world[2] <= 3.0 + 1e-9  # on the pointed wall (the paper's lift), never behind it
    assert_safe(res, cand, VerifierConfig())


def _flying_pixel_scene() -> np.ndarray:
    """A post at 1.5 m (columns 28..35) in front of a wall at 6 m, with the flying pixels a
    stereo/ToF camera gives at its edges: interpolated depths between the two surfaces."""
    d = wall(6.0)
    d[:, 28:36] = 1.5
    for k, z in enumerate((2.6, 3.7, 4.8)):
        d[:, 36 + k] = z  # right edge
        d[:, 27 - k] = z  # left edge
    return d


def test_flying_pixels_at_an_edge_are_obstacles_and_the_goal_keeps_its_clearance():
    d = _flying_pixel_scene()
    P = reading_points(CAM, d)
    esdf = EsdfMap(EsdfConfig())
    esdf.integrate(d, CAM, T_LEVEL)
    # the post and the flying pixels beside it are obstacles (phantoms at worst), never free
    uv = np.array([[31.5, 23.5], [36.0, 23.5], [38.0, 23.5], [26.0, 23.5]])
    pts = transform_points(T_LEVEL, CAM.back_project(uv, np.array([1.5, 2.6, 4.8, 3.7])))
    assert np.all(esdf.query(pts)[0] <= 0.1 + 1e-6)
    accepted = 0
    for u in (27.0, 36.0, 38.0, 40.0, 44.0):  # on the flying pixels and just beside them
        cand = CandidateGoal((u, 23.5), d, None, 16.0, T_ID, CAM)
        res = Verifier().verify(cand)
        if not res.accepted:
            continue
        accepted += 1
        assert_safe(res, cand, VerifierConfig())
        assert res.goal_world[2] < 6.0  # never behind the wall
        if u >= 40.0:  # pointing at the wall beside the post: the path clears the post and its edge
            assert segment_clearance(P[P[:, 2] < 5.9], res.goal_world) >= R_M - 1e-6
    assert accepted >= 1


@FAST
@given(
    bad=st.sampled_from(NO_READING),
    hole=st.tuples(st.integers(0, 47), st.integers(0, 47), st.integers(0, 63), st.integers(0, 63)),
    uv=st.tuples(st.floats(0.0, 63.0), st.floats(0.0, 47.0)),
    post_m=st.floats(0.8, 4.0),
)
def test_the_verifier_never_puts_a_goal_through_or_behind_a_reading(bad, hole, uv, post_m):
    """Any pixel of a post-in-front-of-a-wall scene with flying pixels and a hole of any kind of
    no reading: an accepted goal's straight path from the camera clears every reading by r and
    stays in front of the wall."""
    d = _flying_pixel_scene()
    d[d == 1.5] = post_m
    r0, r1, c0, c1 = sorted(hole[:2]) + sorted(hole[2:])
    d[r0 : r1 + 1, c0 : c1 + 1] = bad
    cand = CandidateGoal(uv, d, None, 16.0, T_ID, CAM)
    res = Verifier().verify(cand)
    if res.accepted:
        assert_safe(res, cand, VerifierConfig())  # the path clears every obstacle of the rule by r
        assert res.goal_world[2] < 6.0  # never behind the wall


def test_a_pixel_in_a_millimetre_frame_never_gives_a_goal_through_the_wall():
    """What the refusal prevents: the same wall at 1.5 m read as 1500 m would be a far target
    whose goal lies 7 m out, through the wall. Converted by the rule, the goal is in front."""
    counts = np.full(CAM.shape, 1500, np.uint16)
    with pytest.raises(VerifierInputError):
        CandidateGoal((31.5, 23.5), counts, None, 16.0, T_ID, CAM)
    res = Verifier().verify(CandidateGoal((31.5, 23.5), depth_from_counts(counts, 1000.0), None, 16.0, T_ID, CAM))
    assert res.accepted and res.goal_world[2] <= 1.5


# -- the pilot's per-frame step ----------------------------------------------------------------


@pytest.fixture(scope="module")
def pilot_factory():
    from planning.planner import Planner

    planner = Planner(PilotConfig().planner)

    def make() -> OnFlyPilot:
        pilot = OnFlyPilot(PilotConfig(), ScriptedVlm("perfect"), ClockRuntime(), planner=planner)
        pilot.begin("Fly to the door.", 0.0)
        return pilot

    return make


def _frame(t_s: float, p, depth=None, name: str = "f") -> Observation:
    T = body_transform(np.asarray(p, float), 0.0) @ T_BODY_CAM
    return obs_of(wall(4.0) if depth is None else depth, T=T, t_s=t_s, frame_id=f"{name}@{t_s}")


def _wall_point(p) -> np.ndarray:
    """A point on the 4 m wall straight ahead (east) of a level camera at ``p``."""
    return np.asarray(p, float)[None] + [[4.0, 0.0, 0.0]]


def test_frames_with_duplicated_or_backward_timestamps_are_skipped_and_counted(pilot_factory):
    pilot = pilot_factory()
    p = np.array([0.0, 0.0, 1.5])
    pilot._on_frame(_frame(1.0, p, name="a"))
    seen = int(pilot.esdf.known_grid.sum())
    newer_elsewhere = wall(2.0)  # would add an obstacle at 2 m if taken
    for t in (1.0, 0.5, -3.0):  # duplicated, older, far in the past
        pilot._on_frame(_frame(t, p, newer_elsewhere, name="old"))
    assert pilot.frames_stale == 3 and pilot.latest.frame_id == "a@1.0"
    assert int(pilot.esdf.known_grid.sum()) == seen  # the map did not take them
    assert [e.kind for e in pilot.events].count("stale_frame") == 3
    pilot._on_frame(_frame(1.5, p, name="b"))  # time moves on: taken
    assert pilot.latest.frame_id == "b@1.5" and pilot.frames_stale == 3


def test_an_odometry_reset_forgets_the_map_and_drops_the_goal(pilot_factory):
    pilot = pilot_factory()
    p0 = np.array([0.0, 0.0, 1.5])
    pilot._on_frame(_frame(1.0, p0))
    assert pilot.esdf.is_free(p0[None] + [[2.0, 0.0, 0.0]]).all()  # seen free in front
    assert not pilot.esdf.is_free(_wall_point(p0)).any()
    pilot.goal_world = p0 + [2.0, 0.0, 0.0]
    pilot.mode = PilotMode.NAVIGATING
    # normal flight and gusts do not trigger it: 0.5 m in 0.5 s, 1.9 m in 0.5 s
    pilot._on_frame(_frame(1.5, p0 + [0.5, 0.0, 0.0]))
    pilot._on_frame(_frame(2.0, p0 + [0.5, 1.9, 0.0]))
    assert pilot.odometry_resets == 0 and pilot.mode is PilotMode.NAVIGATING
    # the estimator re-initialises: 6 m sideways in 0.1 s
    jumped = p0 + [0.5, 7.9, 0.0]
    pilot._on_frame(_frame(2.1, jumped, depth=np.full(CAM.shape, np.nan, np.float32)))
    assert pilot.odometry_resets == 1 and [e.kind for e in pilot.events].count("odometry_reset") == 1
    assert pilot.goal_world is None and pilot.mode is PilotMode.HOLDING
    # what the old frames saw is forgotten: the space ahead is unknown, an obstacle, again
    assert not pilot.esdf.known(p0[None] + [[2.0, 0.0, 0.0]]).any()
    assert not pilot.esdf.known(jumped[None] + [[2.0, 0.0, 0.0]]).any()


def test_the_pilot_ticks_through_bad_frames_without_crashing_and_holds(pilot_factory):
    """Frames with holes of every kind, an all-invalid frame, far garbage readings: the pilot's
    tick maps them and plans; nothing ahead beyond the body sphere becomes free where nothing
    was read, so the plan stays short of the unseen space."""
    from planning.trajectory import VehicleState

    pilot = pilot_factory()
    p = np.array([0.0, 0.0, 1.5])
    d = wall(4.0)
    d[10:30, 20:44] = np.nan
    d[:, :6] = -np.inf
    d[0] = 1e6
    frames = [d, np.full(CAM.shape, np.nan, np.float32), np.zeros(CAM.shape, np.float32)]
    for k, depth in enumerate(frames):
        t = 0.5 * (k + 1)
        tick = pilot.tick(t, VehicleState(t, p, np.zeros(3), 0.0), _frame(t, p, depth))
        assert tick.mode is not PilotMode.FINISHED
        if tick.trajectory is not None:
            assert np.all(np.isfinite(tick.trajectory.p))
            assert np.max(np.linalg.norm(tick.trajectory.p - p, axis=1)) < 4.0 - 0.45
    assert not pilot.esdf.is_free(_wall_point(p) + [[0.3, 0.0, 0.0]]).any()


# -- the camera channel --------------------------------------------------------------------------


def _tampered(obs: Observation, **fields) -> bytes:
    payload = encode_observation(obs)[8:]
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    data.update(fields)
    buf = io.BytesIO()
    np.savez(buf, **data)
    return buf.getvalue()


def test_frames_over_the_wire_keep_their_holes_and_bad_ones_are_refused():
    d = wall()
    d[0, :5] = [0.0, np.nan, np.inf, -np.inf, -1.0]
    obs = obs_of(d)
    back = decode_observation(encode_observation(obs)[8:])
    np.testing.assert_array_equal(back.depth_m, d)  # NaN == NaN here: holes arrive as holes
    cases = {
        "raw sensor counts": dict(depth_m=np.full(CAM.shape, 1500, np.uint16)),
        "was it given in millimetres": dict(depth_m=np.full(CAM.shape, 1500.0, np.float32)),
        r"depth_m must have shape \(48, 64": dict(depth_m=np.ones((48, 63), np.float32)),
        "non-finite": dict(T_world_cam=np.full((4, 4), np.nan)),
        "reflection": dict(T_world_cam=np.diag([1.0, -1.0, 1.0, 1.0])),
        "principal point": dict(intrinsics=np.array([64, 48, 32.0, 32.0, 320.0, 240.0])),
        "focal lengths": dict(intrinsics=np.array([64, 48, 0.0, 32.0, 31.5, 23.5])),
        "t_s must be finite": dict(t_s=np.array(np.nan)),
    }
    for match, fields in cases.items():
        with pytest.raises(FrameChannelError, match=match):
            decode_observation(_tampered(obs, **fields))


# -- recordings: the TUM reader and `onfly replay` -----------------------------------------------


def _tum(root: Path, depth_pngs: list[np.ndarray], times: list[float], positions, intrinsics="32 32 31.5 23.5", depth_list=None) -> Path:
    """A TUM RGB-D folder of the given 16-bit depth images (scale 5000), level camera poses."""
    (root / "depth").mkdir(parents=True)
    (root / "rgb").mkdir()
    rgb_lines, depth_lines, gt = [], [], []
    for k, (png, t) in enumerate(zip(depth_pngs, times)):
        cv2.imwrite(str(root / "depth" / f"{k}.png"), png)
        cv2.imwrite(str(root / "rgb" / f"{k}.png"), np.full((*png.shape[:2], 3), 90, np.uint8))
        rgb_lines.append(f"{t:.6f} rgb/{k}.png")
        depth_lines.append(f"{t:.6f} depth/{k}.png")
    qx, qy, qz, qw = Rotation.from_matrix(T_BODY_CAM[:3, :3]).as_quat()  # a level camera looking east
    for t, p in zip(sorted(set(times)), positions):
        gt.append(f"{t:.6f} {p[0]} {p[1]} {p[2] + 1.5} {qx} {qy} {qz} {qw}")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_list or depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if intrinsics is not None:
        (root / "intrinsics.txt").write_text(intrinsics + "\n")
    return root


def _counts(wall_m: float = WALL_M) -> np.ndarray:
    return np.full(CAM.shape, int(wall_m * 5000), np.uint16)


def test_tum_recording_with_saturated_and_missing_pixels_and_out_of_order_lines(tmp_path):
    a, b, c = _counts(), _counts(), _counts()
    a[:4] = 65535  # saturated: no reading, not 13.1 m
    b[:, :4] = 0
    times = [0.0, 0.1, 0.2]
    lines = ["0.200000 depth/2.png", "0.000000 depth/0.png", "0.100000 depth/1.png"]  # out of order on disk
    root = _tum(tmp_path / "tum", [a, b, c], times, [(0, 0, 0)] * 3, depth_list=lines)
    frames = list(TumReader(root))
    assert [f.t_s for f in frames] == times  # read in time order
    assert np.all(frames[0].depth_m[:4] == 0.0) and frames[0].depth_m[4, 0] == np.float32(WALL_M)
    assert np.all(frames[1].depth_m[:, :4] == 0.0)


def test_tum_depth_older_or_newer_than_its_poses_is_dropped_and_counted(tmp_path):
    """Depth frames outside the ground truth's span (beyond ``max_difference_s``) or between
    poses too far apart have no pose: dropped and counted, never given a stale pose."""
    times = [0.0, 0.1, 0.2, 0.3]
    root = _tum(tmp_path / "tum", [_counts()] * 4, times, [(0, 0, 0)] * 4)
    (root / "groundtruth.txt").write_text("0.100000 0 0 0 0 0 0 1\n0.200000 0 0 0 0 0 0 1\n")
    reader = TumReader(root)
    assert [o.t_s for o in reader] == [0.1, 0.2]
    assert reader.dropped == {"no_rgb": 0, "no_pose": 2}


def test_tum_bad_inputs_fail_before_the_first_frame_naming_the_file(tmp_path):
    with pytest.raises(TumFormatError, match=r"intrinsics \(32\.0, 32\.0, 320\.0, 240\.0\) .*intrinsics\.txt.* 64 x 48"):
        TumReader(_tum(tmp_path / "a", [_counts()], [0.0], [(0, 0, 0)], intrinsics="32 32 320 240"))
    with pytest.raises(TumFormatError, match="focal lengths must be positive"):
        TumReader(_tum(tmp_path / "b", [_counts()], [0.0], [(0, 0, 0)], intrinsics="0 32 31.5 23.5"))
    root = _tum(tmp_path / "c", [_counts()], [0.0], [(0, 0, 0)])
    (root / "groundtruth.txt").write_text("0.000000 0 nan 0 0 0 0 1\n")
    with pytest.raises(TumFormatError, match=r"groundtruth\.txt:1: non-finite value"):
        TumReader(root)
    root = _tum(tmp_path / "d", [(_counts() // 100).astype(np.uint8)], [0.0], [(0, 0, 0)])
    with pytest.raises(TumFormatError, match="16-bit single-channel PNG"):
        TumReader(root)


def test_replay_of_a_recording_with_an_odometry_jump_and_duplicated_stamps_runs_to_the_end(tmp_path):
    """Replay is open loop over what was recorded: a duplicated stamp holds the previous
    velocity (no division by zero), a 6 m pose jump gives a large measured speed that the
    planner answers with a fallback, not a solver error; every frame is processed."""
    times = [0.0, 0.1, 0.1, 0.2, 0.3]
    positions = [(0, 0, 0), (0.05, 0, 0), (6.05, 0, 0), (6.1, 0, 0)]  # one pose per distinct stamp
    pngs = [_counts() for _ in times]
    pngs[3][:10] = 65535
    root = _tum(tmp_path / "tum", pngs, times, positions)
    with TumReader(root) as src:
        report = replay(src, ReplayConfig(goal_mode="fixed", goal_world=(0.0, 0.0, 2.0)), progress=False)
    assert report.frames == 5 == len(report.per_frame)
    speeds = [f.speed_mps for f in report.per_frame]
    assert all(np.isfinite(speeds)) and speeds[2] == pytest.approx(speeds[1])  # held over the duplicate
    assert max(speeds) > 50.0  # the jump is visible in the report, not hidden
    assert all(np.isfinite(f.planner_ms) for f in report.per_frame)


def test_onfly_replay_reports_a_bad_recording_in_one_line(tmp_path, capsys):
    root = _tum(tmp_path / "tum", [_counts()], [0.0], [(0, 0, 0)], intrinsics="32 32 319.5 239.5")
    rc = main(["replay", str(root), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("onfly replay: error: ") and "principal point" in lines[0]


def test_onfly_replay_of_a_recording_with_holes_and_saturation_keeps_unread_space_unknown(tmp_path, capsys):
    a = _counts()
    a[20:30, 20:40] = 0
    a[:5] = 65535
    root = _tum(tmp_path / "tum", [a, a.copy()], [0.0, 0.1], [(0, 0, 0), (0, 0, 0)])
    out = tmp_path / "r.json"
    rc = main(["replay", str(root), "--no-progress", "--json", str(out)])
    assert rc == 0, capsys.readouterr().err
    data = json.loads(out.read_text())
    assert data["frames"] == 2 == len(data["per_frame"])
    # the camera sits 3 m from a wall with a hole: it is never "clear" by more than the wall allows
    assert all(f["path_clearance_m"] <= WALL_M + 1e-6 for f in data["per_frame"])
