"""Open-loop replay (onfly.replay): goals, finite-difference state, path clearance, agents and
verifier statistics on an OnFly log of the embedded world, config and input errors.

The real-recording end-to-end run (7-Scenes kitchen, JSON, rerun file) is in
tests/test_replay_cli.py.
"""

from __future__ import annotations

import json
import math
from itertools import islice
from pathlib import Path

import numpy as np
import pytest

from onfly.agents import vlm_image
from onfly.logs import LogWriter
from onfly.observation import Observation
from onfly.readers import open_source
from onfly.replay import DecisionRecord, ReplayConfig, ReplayConfigError, ReplayError, _verifier_stats, replay
from planning.camera import PinholeCamera
from planning.esdf_config import EsdfConfig
from planning.frames import body_transform, cam_transform_from_body
from planning.verifier import CandidateGoal, Verifier, VerifierConfig

CAMERA = PinholeCamera.from_fov(32, 24, 90.0, 60.0)


class ListSource:
    """A source over a list of observations (what the readers look like to replay)."""

    kind = "list"

    def __init__(self, observations, path="synthetic"):
        self.observations = list(observations)
        self.path = Path(path)

    def __iter__(self):
        return iter(self.observations)

    def __len__(self):
        return len(self.observations)


def _obs(t_s: float, x: float, depth: float, index: int) -> Observation:
    """Camera at (x, 0, 1.5) looking along +x (level body, yaw 0); constant z-depth (0 = none)."""
    T = cam_transform_from_body(body_transform(np.array([x, 0.0, 1.5]), 0.0))
    return Observation(
        t_s=t_s,
        rgb=np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8),
        depth_m=np.full((CAMERA.height, CAMERA.width), depth, np.float32),
        T_world_cam=T,
        camera=CAMERA,
        frame_id=f"syn/{index}",
    )


TIMES = [0.0, 1.0, 2.0, 4.0, 5.0]
XS = [0.0, 1.0, 3.0, 4.0, 8.0]


def _track(depth: float = 0.0) -> ListSource:
    return ListSource(_obs(t, x, depth, i) for i, (t, x) in enumerate(zip(TIMES, XS)))


# -- goals and state ---------------------------------------------------------------------------


def test_future_pose_goal_is_interpolated_logged_position_and_speed_is_backward_difference():
    report = replay(_track(), ReplayConfig(future_pose_s=1.5), progress=False)
    assert report.frames == report.frames_read == 5
    # t + 1.5 = 1.5 -> x 2.0; 2.5 -> 3.25; 3.5 -> 3.75; beyond the end -> last position 8
    np.testing.assert_allclose([f.goal_m[0] for f in report.per_frame], [2.0, 3.25, 3.75, 8.0, 8.0], atol=1e-12)
    np.testing.assert_allclose([f.goal_m[1:] for f in report.per_frame], [[0.0, 1.5]] * 5, atol=1e-12)
    np.testing.assert_allclose([f.speed_mps for f in report.per_frame], [0.0, 1.0, 2.0, 0.5, 4.0], atol=1e-12)
    assert report.logged_speed_max_mps == pytest.approx(4.0)
    assert report.duration_s == 5.0
    assert report.vlm is None and report.verifier is None
    assert set(report.latency_ms) == {"esdf", "planner"}
    assert all(lat.n == 5 and lat.p95_ms >= lat.median_ms > 0 for lat in report.latency_ms.values())


def test_every_n_and_max_frames_skip_frames_but_keep_the_difference_state():
    report = replay(_track(), ReplayConfig(every_n=2, future_pose_s=1.5), progress=False)
    assert [f.index for f in report.per_frame] == [0, 2, 4]
    assert report.frames_read == 5
    # frame 2's velocity comes from frame 1, read but not processed
    np.testing.assert_allclose([f.speed_mps for f in report.per_frame], [0.0, 2.0, 4.0], atol=1e-12)
    short = replay(_track(), ReplayConfig(every_n=2, max_frames=2, future_pose_s=1.5), progress=False)
    assert [f.index for f in short.per_frame] == [0, 2]


def test_fixed_goal_is_handed_to_the_planner_every_frame():
    report = replay(_track(), ReplayConfig(goal_mode="fixed", goal_world=(1.0, 2.0, 3.0)), progress=False)
    assert [f.goal_m for f in report.per_frame] == [(1.0, 2.0, 3.0)] * 5
    assert report.goal_mode == "fixed"


# -- path clearance ----------------------------------------------------------------------------


def test_path_clearance_is_the_distance_from_the_camera_to_the_observed_wall():
    # a wall 1 m in front of a camera at rest; the clamp raised so 1 m is not clamped. The
    # shell of clear_margin_m in front of the wall stays unknown (an obstacle): no ray passed
    # it, and the body sphere leaves what the camera looks at to the camera. The sphere runs
    # to its full radius above (body_clear_above_m=None): capped, the space 0.65 m over the
    # camera, which it never saw, would be the nearest obstacle
    source = ListSource(_obs(0.1 * i, 0.0, 1.0, i) for i in range(3))
    esdf = EsdfConfig(max_distance_m=2.0, body_clear_above_m=None)
    config = ReplayConfig(goal_mode="fixed", goal_world=(0.0, 0.0, 1.5), esdf=esdf)
    report = replay(source, config, progress=False)
    expected = 1.0 - esdf.clear_margin_m
    assert [f.path_clearance_m for f in report.per_frame] == pytest.approx([expected] * 3, abs=0.1)
    assert report.path_clearance_min_m == pytest.approx(expected, abs=0.1)
    assert report.planner_clearance_min_m > 0.45  # the plan toward the current position keeps d_safe


def test_path_clearance_exposes_a_pose_inside_the_mapped_wall():
    # frame 1 claims the camera moved 1.05 m forward, onto the wall frame 0 saw (its voxel
    # centre, where the field's zero level lies); it has no depth readings, so the map keeps
    # the wall and the camera sits in it
    source = ListSource([_obs(0.0, 0.0, 1.0, 0), _obs(0.5, 1.05, 0.0, 1)])
    config = ReplayConfig(goal_mode="fixed", goal_world=(0.0, 0.0, 1.5), esdf=EsdfConfig(body_clear_above_m=None))
    report = replay(source, config, progress=False)
    assert report.per_frame[0].path_clearance_m > 0.8  # the wall at 1 m less the unknown shell
    assert report.path_clearance_min_m <= 0.01
    assert report.path_clearance_min_index == 1


# -- agents on an OnFly log of the embedded world -----------------------------------------------------


URBAN_TASK = "urban_block-o01"
N_LOG_FRAMES = 12


@pytest.fixture(scope="module")
def urban_log(tmp_path_factory) -> Path:
    """12 frames (0.5 s apart) of the embedded world flying toward the red van of urban_block-o01."""
    from onfly.bench.tasks import load_tasks
    from onfly.world.world import World
    from planning.straight_line import straight_line_plan
    from planning.trajectory import VehicleState

    task = next(t for t in load_tasks() if t.task_id == URBAN_TASK)
    world = World.from_scene(
        task.scene,
        camera=PinholeCamera.from_fov(320, 214, 90.0, 60.0),
        initial_state=VehicleState(0.0, task.start.position_m, [0, 0, 0], task.start.yaw_rad),
    )
    path = tmp_path_factory.mktemp("replay") / "urban"
    aim = np.array([2.6, -18.8, 1.5])
    with LogWriter(path, meta={"instruction": task.instruction, "task": task.task_id}) as writer:
        for _ in range(N_LOG_FRAMES):
            writer.write(world.observe())
            world.set_trajectory(straight_line_plan(world.state, aim, v_max_mps=0.6, a_max_mps2=0.6, yaw_rate_max_rps=0.4, dt_s=0.1, steps=40))
            world.step(0.5)
    return path


@pytest.fixture(scope="module")
def urban_report(urban_log):
    config = ReplayConfig(goal_mode="agents", instruction="Fly to the red delivery van.", vlm="sim:perfect")
    with open_source(urban_log) as source:
        return replay(source, config, progress=False)


def test_agents_replay_reports_every_stage_and_the_verifier(urban_report):
    r = urban_report
    assert r.kind == "onfly-log" and r.frames == N_LOG_FRAMES
    assert set(r.latency_ms) == {"esdf", "planner", "features", "verifier", "decision_vlm", "monitoring_vlm"}
    assert r.vlm == "sim:perfect" and r.vlm_latency == "modelled"
    assert r.latency_ms["decision_vlm"].median_ms == pytest.approx(810.0)  # the modelled Jetson latency
    assert r.decisions == N_LOG_FRAMES == r.latency_ms["verifier"].n
    # monitoring every 2 s of log time once the memory holds two frames: t = 0.5, 2.5, 4.5
    assert r.monitor_calls == 3 == sum(r.monitor_statuses.values())
    v = r.verifier
    assert v.candidates == N_LOG_FRAMES
    assert v.accepted + sum(v.rejected.values()) == v.candidates
    assert v.accepted == r.goals_accepted > 0
    assert sum(v.refinement_notes.values()) == v.candidates
    gating = [d.gating_factor for d in r.decision_log if d.rejection is None]
    assert v.range_gated == sum(g < 0.95 for g in gating)
    assert v.gating_factor_median == pytest.approx(float(np.median(gating)))
    assert r.path_clearance_min_m > 0


def test_agents_goal_is_the_verified_goal_of_the_same_frame(urban_report):
    for frame, decision in zip(urban_report.per_frame, urban_report.decision_log):
        assert decision.frame_index == frame.index
        if decision.goal_world_m is not None:
            assert frame.goal_m == decision.goal_world_m


def test_agents_verifier_record_matches_a_fresh_verification_of_the_logged_frame(urban_log, urban_report):
    from vlm.sim import SimulatedVlm

    k = N_LOG_FRAMES - 1
    decision = urban_report.decision_log[k]
    with open_source(urban_log) as source:
        obs = next(islice(source, k, None))
    feats = SimulatedVlm("perfect", seed=0).features(vlm_image(obs))
    candidate = CandidateGoal(decision.pixel_uv, obs.depth_m, feats.grid, feats.patch_px, obs.T_world_cam, obs.camera)
    verified = Verifier(VerifierConfig()).verify(candidate)
    assert verified.accepted == (decision.rejection is None)
    np.testing.assert_array_equal(verified.goal_world, decision.goal_world_m)
    assert verified.record.gating_factor == decision.gating_factor
    assert verified.record.refinement_note.value == decision.refinement_note


def test_report_to_dict_is_strict_json(urban_report):
    d = urban_report.to_dict()
    text = json.dumps(d, allow_nan=False)
    back = json.loads(text)
    assert back["frames"] == N_LOG_FRAMES
    assert back["latency_ms"]["esdf"]["n"] == N_LOG_FRAMES
    assert len(back["per_frame"]) == N_LOG_FRAMES and len(back["decision_log"]) == N_LOG_FRAMES
    assert back["config"]["verifier"]["tau"] == 0.5
    assert "per_frame" not in urban_report.to_dict(per_frame=False)


def test_simulated_vlm_refuses_frames_without_annotations():
    config = ReplayConfig(goal_mode="agents", instruction="fly to the door", vlm="sim:perfect")
    with pytest.raises(ReplayError, match="needs per-frame annotations.*frame 'syn/0' has none"):
        replay(_track(), config, progress=False)


class PointingVlm:
    """A fake backend: always points at ``uv``, always says CONTINUE, no features, no
    decomposition (the deterministic splitter takes over)."""

    name = "fake:pointing"

    def __init__(self, uv):
        self.uv = uv
        self.closed = False

    def complete(self, messages, images=(), **kw):
        from vlm.prompts import DecisionPrompt, MonitorPrompt, parse_prompt
        from vlm.types import CallStatus, VlmResponse

        prompt = parse_prompt(messages)
        if isinstance(prompt, DecisionPrompt):
            return VlmResponse(CallStatus.OK, f'{{"point_2d": [{self.uv[0]}, {self.uv[1]}]}}', latency_s=0.25)
        if isinstance(prompt, MonitorPrompt):
            return VlmResponse(CallStatus.OK, "CONTINUE", latency_s=0.5)
        return VlmResponse(CallStatus.ERROR, error="no decomposition here", latency_s=0.1)

    def features(self, image):
        return None

    def close(self):
        self.closed = True


def test_verifier_moves_a_pixel_beside_a_near_obstacle_and_the_report_counts_it():
    # left half of the image 1 m away (near field: an obstacle), right half 5 m away; the VLM
    # points at the far wall right beside the edge, where its ray grazes the near half: the
    # geometric-only refinement moves it clear to the right, along the far wall's surface
    def frame(i):
        obs = _obs(0.5 * i, 0.1 * i, 5.0, i)
        obs.depth_m[:, :16] = 1.0
        return obs

    backend = PointingVlm((17.0, 12.0))
    config = ReplayConfig(goal_mode="agents", instruction="fly to the far wall", vlm="http:unused")
    report = replay(ListSource(frame(i) for i in range(3)), config, progress=False, backend=backend)
    assert not backend.closed  # the caller's backend stays open
    assert report.vlm == "fake:pointing" and report.vlm_latency == "measured"
    assert report.subtasks == ("fly to the far wall",) and report.decomposition_source == "fallback"
    assert report.decisions == 3 and report.goals_accepted == 3
    v = report.verifier
    assert (v.candidates, v.accepted, v.moved) == (3, 3, 3)
    assert v.refinement_notes == {"no_features": 3}
    for d in report.decision_log:
        assert d.pixel_uv == (17.0, 12.0) and d.refined_uv[0] > 17.0  # away from the near half
        assert d.pixel_shift_px == pytest.approx(math.hypot(d.refined_uv[0] - 17.0, d.refined_uv[1] - 12.0))
    assert v.pixel_shift_max_px == max(d.pixel_shift_px for d in report.decision_log)
    assert report.latency_ms["decision_vlm"].median_ms == pytest.approx(250.0)
    assert report.monitor_calls == 1 and report.monitor_statuses == {"CONTINUE": 1}  # t = 0.5 only (period 2 s)


# -- verifier statistics -------------------------------------------------------------------------


def _record(shift, gating, rejection=None, note="semantic"):
    return DecisionRecord(0, "s", "ok", (1.0, 1.0), None, shift, gating, note, rejection, None if rejection else (0.0, 0.0, 0.0), "", 1.0)


def test_verifier_stats_counts_moved_gated_and_rejected_exactly():
    records = [
        _record(0.0, 1.0),
        _record(0.4, 0.99),  # below moved_min_px = 0.5
        _record(3.0, 0.90),  # moved, gated
        _record(7.0, 0.50),  # moved, gated
        _record(float("nan"), float("nan"), "no_feasible_pixel"),
        _record(float("nan"), float("nan"), "no_feasible_pixel"),
        _record(float("nan"), float("nan"), "pixel_outside_image", note="not_attempted"),
        DecisionRecord(0, "s", "ok", None, None, float("nan"), float("nan"), None, None, None, "parse: no point", 1.0),
    ]
    s = _verifier_stats(records, ReplayConfig())
    assert (s.candidates, s.accepted, s.moved, s.range_gated) == (7, 4, 2, 2)
    assert s.pixel_shift_median_px == 5.0 and s.pixel_shift_max_px == 7.0
    assert s.gating_factor_median == pytest.approx(0.945)
    assert s.rejected == {"no_feasible_pixel": 2, "pixel_outside_image": 1}
    assert s.refinement_notes == {"semantic": 6, "not_attempted": 1}
    none_moved = _verifier_stats(records[:1], ReplayConfig())
    assert none_moved.moved == 0 and none_moved.pixel_shift_median_px is None


# -- errors ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(goal_mode="teleport"), "goal_mode must be one of"),
        (dict(goal_mode="fixed"), "goal_world is required"),
        (dict(goal_world=(1, 2, 3)), "goal_world is given but goal_mode is 'future_pose'"),
        (dict(goal_mode="fixed", goal_world=(1, 2)), "goal_world must be three finite numbers"),
        (dict(goal_mode="fixed", goal_world=(1, 2, math.nan)), "goal_world must be three finite numbers"),
        (dict(goal_mode="agents"), "instruction is required"),
        (dict(instruction="  "), "instruction must be non-empty"),
        (dict(future_pose_s=0.0), "future_pose_s must be a positive number"),
        (dict(every_n=0), r"every_n must be an integer >= 1"),
        (dict(max_frames=1.5), r"max_frames must be an integer >= 1"),
        (dict(vlm="gpt"), "vlm must be a backend spec"),
        (dict(range_gated_below=1.5), "range_gated_below must be in"),
        (dict(coord_format="polar"), "coord_format must be one of"),
    ],
)
def test_config_errors_name_the_field(kwargs, match):
    with pytest.raises(ReplayConfigError, match=match):
        ReplayConfig(**kwargs)


def test_config_from_dict_fills_nested_configs_and_rejects_unknown_keys():
    c = ReplayConfig.from_dict({"goal_mode": "fixed", "goal_world": [1, 2, 3], "planner": {"v_max_mps": 0.3}, "esdf": {"size_m": [6, 6, 6]}})
    assert c.goal_world == (1.0, 2.0, 3.0) and c.planner.v_max_mps == 0.3 and c.esdf.size_m == (6.0, 6.0, 6.0)
    with pytest.raises(ReplayConfigError, match="unknown replay option 'speed'"):
        ReplayConfig.from_dict({"speed": 1})
    with pytest.raises(ReplayConfigError, match=r"unknown planner option\(s\) \['vmax'\]"):
        ReplayConfig.from_dict({"planner": {"vmax": 1}})


def test_empty_source_is_an_error():
    with pytest.raises(ReplayError, match="empty: no frames to replay"):
        replay(ListSource([], path="empty"), ReplayConfig(), progress=False)


def test_replay_volume_is_validated_and_clamps_the_goal_the_planner_sees():
    cfg = ReplayConfig(goal_mode="fixed", goal_world=(30.0, 0.0, 9.0), volume=(-5, -5, 0, 5, 5, 3))
    assert cfg.flight_volume.to_list() == [-5.0, -5.0, 0.0, 5.0, 5.0, 3.0]
    report = replay(_track(), cfg, progress=False)
    assert len(report.per_frame) == 5
    # the goal keeps the planner's safety distance plus its drift margin (1 % of the track flown
    # before the frame: 0, 0, 1, 3 and 4 m) from the faces it was clamped onto
    for f, flown in zip(report.per_frame, [0.0, 0.0, 1.0, 3.0, 4.0]):
        m = cfg.planner.d_safe_m + cfg.planner.volume_drift_fraction * flown
        np.testing.assert_allclose(f.goal_m, [5 - m, 0.0, 3 - m], atol=1e-12)
    with pytest.raises(ReplayConfigError, match="volume"):
        ReplayConfig(volume=(0, 0, 0, 1, 1))
    with pytest.raises(ReplayConfigError, match="volume"):
        ReplayConfig(volume=(0, 0, 0, 1, 1, 0))
