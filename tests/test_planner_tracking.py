"""The planner against a vehicle that does not follow its plans exactly.

- Plans start from the previous plan's reference state while the measured position is within
  ``reference_reset_m`` of it (EGO-Planner's ``planFromCurrentTraj``), so the vehicle's position
  controller corrects the tracking error; beyond it, or when switched off, from the measurement.
- The clearance and flight-volume margin grows with the measured tracking error (the largest of
  the last ``tracking_window_s``, capped) and is 0 under perfect tracking.
- In closed loop with the realistic world's PX4 position controller and Dryden gusts
  (``onfly.world.realism``) a hover next to a wall never touches it; with plans re-based on the
  measured state every step and no margin (the planner before this change) the gusts overpower
  the planner's 0.6 m/s^2 and push the vehicle through the wall.
"""

from __future__ import annotations

import numpy as np
import pytest

from onfly.world.realism import ControllerModel, GustProcess, WindModel
from onfly.world.vehicle import SimVehicle
from planning.analytic_field import AnalyticField, HalfSpace
from planning.planner import InflatedField, Planner, PlannerInputError, run_closed_loop
from planning.planner_config import PlannerConfig, PlannerConfigError
from planning.trajectory import VehicleState
from planning.volume import FlightVolume

GROUND = HalfSpace(np.zeros(3), np.array([0.0, 0.0, 1.0]))
#: a wall at x = 3 (solid for x >= 3) over the ground
WALL = AnalyticField(half_spaces=(HalfSpace(np.array([3.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])), GROUND))
OPEN = AnalyticField(half_spaces=(GROUND,))
BODY_RADIUS_M = 0.25


def _state(t, p, v=(0.0, 0.0, 0.0)):
    return VehicleState(float(t), np.asarray(p, float), np.asarray(v, float), 0.0)


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner(PlannerConfig())


def test_plan_starts_from_the_reference_within_the_reset_distance(planner):
    planner.reset()
    first = planner.step(_state(0.0, [0.0, 0.0, 1.5]), np.array([5.0, 0.0, 1.5]), OPEN)
    assert not first.from_reference and np.isnan(first.tracking_error_m)
    p_ref, v_ref, a_ref, _, _ = first.trajectory.sample(0.1)
    measured = p_ref + np.array([0.0, 0.3, 0.0])  # a gust pushed the vehicle 0.3 m sideways
    r = planner.step(_state(0.1, measured, v_ref + np.array([0.0, 0.4, 0.0])), np.array([5.0, 0.0, 1.5]), OPEN)
    assert r.from_reference
    assert r.tracking_error_m == pytest.approx(0.3, abs=1e-9)
    np.testing.assert_allclose(r.trajectory.p[0], p_ref, atol=1e-12)
    np.testing.assert_allclose(r.trajectory.v[0], v_ref, atol=1e-12)
    # the plan stays within the planner's own limits although the vehicle is faster
    assert np.linalg.norm(r.trajectory.v, axis=1).max() <= 0.6 * 1.01


def test_plan_restarts_from_the_measurement_beyond_the_reset_distance(planner):
    planner.reset()
    first = planner.step(_state(0.0, [0.0, 0.0, 1.5]), np.array([5.0, 0.0, 1.5]), OPEN)
    p_ref = first.trajectory.sample(0.1)[0]
    far = p_ref + np.array([0.0, 1.6, 0.0])  # beyond reference_reset_m = 1.5
    r = planner.step(_state(0.1, far), np.array([5.0, 0.0, 1.5]), OPEN)
    assert not r.from_reference
    assert r.tracking_error_m == pytest.approx(1.6, abs=1e-9)
    np.testing.assert_allclose(r.trajectory.p[0], far, atol=1e-12)


def test_reference_start_off_and_a_stale_plan_use_the_measurement():
    pl = Planner(PlannerConfig(reference_start=False))
    pl.step(_state(0.0, [0.0, 0.0, 1.5]), np.array([5.0, 0.0, 1.5]), OPEN)
    p = np.array([0.01, 0.2, 1.5])
    r = pl.step(_state(0.1, p), np.array([5.0, 0.0, 1.5]), OPEN)
    assert not r.from_reference and r.tracking_error_m > 0.19  # measured all the same
    np.testing.assert_allclose(r.trajectory.p[0], p, atol=1e-12)
    pl = Planner(PlannerConfig())
    pl.step(_state(0.0, [0.0, 0.0, 1.5]), np.array([5.0, 0.0, 1.5]), OPEN)
    r = pl.step(_state(0.6, p), np.array([5.0, 0.0, 1.5]), OPEN)  # older than reference_max_age_s
    assert not r.from_reference and np.isnan(r.tracking_error_m)
    np.testing.assert_allclose(r.trajectory.p[0], p, atol=1e-12)


def test_margin_is_the_recent_peak_error_capped_and_expires():
    cfg = PlannerConfig(tracking_margin_max_m=0.5, tracking_window_s=2.0)
    pl = Planner(cfg)
    goal = np.array([0.0, 0.0, 1.5])
    r = pl.step(_state(0.0, goal), goal, OPEN)
    # hovering in place: the reference is the goal; offsets are the measured error
    t = 0.1
    r = pl.step(_state(t, goal + [0.3, 0.0, 0.0]), goal, OPEN)
    assert r.tracking_margin_m == pytest.approx(0.3, abs=1e-6)
    t += 0.1
    r = pl.step(_state(t, r.trajectory.sample(t)[0] + [0.0, 0.8, 0.0]), goal, OPEN)
    assert r.tracking_margin_m == pytest.approx(0.5)  # 0.8 measured, capped
    # perfect tracking from now on: the peak leaves the window after 2 s
    margins = []
    for _ in range(30):
        t += 0.1
        r = pl.step(_state(t, r.trajectory.sample(t)[0], r.trajectory.sample(t)[1]), goal, OPEN)
        margins.append(r.tracking_margin_m)
    assert margins[10] == pytest.approx(0.5)  # 1.1 s after the 0.8 m error
    assert margins[-1] < 1e-9
    off = Planner(PlannerConfig(tracking_margin_max_m=0.0))
    off.step(_state(0.0, goal), goal, OPEN)
    assert off.step(_state(0.1, goal + [0.3, 0.0, 0.0]), goal, OPEN).tracking_margin_m == 0.0


def test_margin_keeps_goal_and_plan_farther_from_the_wall_and_the_volume():
    cfg = PlannerConfig()
    volume = FlightVolume(np.array([-10.0, -1.5, 0.0]), np.array([10.0, 10.0, 4.0]))
    goal = np.array([2.9, -1.4, 1.5])  # at the wall, at the volume's -y face
    calm = Planner(cfg)
    r0 = calm.step(_state(0.0, [0.0, 0.0, 1.5]), goal, WALL, volume=volume)
    assert r0.tracking_margin_m == 0.0
    assert r0.goal_used[0] == pytest.approx(3.0 - cfg.d_safe_m - cfg.goal_clearance_margin_m, abs=0.02)
    assert r0.goal_used[1] == pytest.approx(-1.5 + cfg.body_radius_m, abs=1e-9)
    gusty = Planner(cfg)
    r = gusty.step(_state(0.0, [0.0, 0.0, 1.5]), goal, WALL, volume=volume)
    ref = r.trajectory.sample(0.1)[0]
    r = gusty.step(_state(0.1, ref + [-0.4, 0.0, 0.0]), goal, WALL, volume=volume)
    assert r.tracking_margin_m == pytest.approx(0.4, abs=1e-9)
    need = cfg.d_safe_m + cfg.goal_clearance_margin_m + 0.4
    assert WALL.query(r.goal_used[None])[0][0] >= need - 0.02
    assert r.goal_used[1] >= -1.5 + cfg.body_radius_m + 0.4 - 1e-9
    # every knot of the plan keeps d_safe + margin from the true wall and stays in the shrunk box
    for _ in range(60):
        t = r.trajectory.t0_s + 0.1
        p, v = r.trajectory.sample(t)[0:2]
        r = gusty.step(_state(t, p + [0.0, 0.0, 0.0], v), goal, WALL, volume=volume)
    d = WALL.query(r.trajectory.p[1:])[0]
    assert r.tracking_margin_m == pytest.approx(0.4, abs=1e-9)  # 6 s later: still in the window
    assert d.min() >= cfg.d_safe_m + 0.4 - cfg.safety_tolerance_m
    assert r.trajectory.p[1:, 1].min() >= -1.5 + cfg.body_radius_m + 0.4 - cfg.safety_tolerance_m


def test_perfect_tracking_keeps_the_margin_at_zero(planner):
    planner.reset()
    log = run_closed_loop(planner, _state(0.0, [0.0, 0.0, 1.5]), np.array([2.0, 1.0, 1.5]), WALL, max_steps=80)
    assert log.reached
    assert all(r.from_reference for r in log.results[1:])
    assert max(r.tracking_margin_m for r in log.results) < 1e-9


def test_inflated_field_shifts_distance_and_forwards_the_rest():
    class Known:
        def query(self, points):
            return np.full(len(points), 2.0), np.tile([1.0, 0.0, 0.0], (len(points), 1))

        def known(self, points):
            return np.ones(len(points), bool)

    f = InflatedField(Known(), 0.5)
    d, g = f.query(np.zeros((3, 3)))
    np.testing.assert_allclose(d, 1.5)
    np.testing.assert_allclose(g[:, 0], 1.0)
    assert f.known(np.zeros((2, 3))).all()
    with pytest.raises(PlannerInputError, match="margin_m"):
        InflatedField(Known(), -0.1)


@pytest.mark.parametrize("name", ["reference_reset_m", "reference_max_age_s", "tracking_window_s"])
def test_bad_tracking_fields_are_named(name):
    with pytest.raises(PlannerConfigError, match=name):
        PlannerConfig(**{name: 0.0})
    with pytest.raises(PlannerConfigError, match="tracking_margin_max_m"):
        PlannerConfig(tracking_margin_max_m=-0.1)


def _hover_by_a_wall(cfg: PlannerConfig, seed: int, seconds: float = 40.0) -> tuple[float, float, float]:
    """Hover 1 m from the wall under PX4's position controller and light Dryden turbulence
    (the realistic profile's models); the true body centre's least distance to the wall over
    every 10 ms integration step, the largest true speed and the farthest distance from the
    hover point."""
    pl = Planner(cfg)
    vehicle = SimVehicle(
        _state(0.0, [0.0, 0.0, 1.5]), controller=ControllerModel(), gusts=GustProcess(WindModel.dryden(7.7, 1.5), seed)
    )
    goal = np.array([2.0, 0.0, 1.5])
    least, fastest, farthest = np.inf, 0.0, 0.0
    for _ in range(int(round(seconds / 0.1))):
        r = pl.step(vehicle.state, goal, WALL)
        vehicle.set_trajectory(r.trajectory)
        _, P = vehicle.step(0.1)
        least = min(least, float(WALL.query(P)[0].min()))
        fastest = max(fastest, float(np.linalg.norm(vehicle.state.v)))
        farthest = max(farthest, float(np.linalg.norm(P - goal, axis=1).max()))
    return least, fastest, farthest


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gusts_never_push_a_hover_into_the_wall(seed):
    least, fastest, farthest = _hover_by_a_wall(PlannerConfig(), seed)
    assert least > BODY_RADIUS_M + 0.1, least
    assert fastest < 1.5, fastest
    assert farthest < 2.5, farthest  # the margin moves the hover point ~1 m back from the wall


@pytest.mark.slow  # ~80 s: the run-away planner fails and re-solves every step
def test_plans_rebased_on_the_measurement_lose_to_the_gusts():
    """The cause, kept as a test: every plan starting at the measured state hands the gust
    rejection to the planner's 0.6 m/s^2, which light turbulence (0.45 1/s x 1.5 m/s RMS)
    exceeds; the vehicle runs away (through the wall, or off into the open)."""
    old = PlannerConfig(reference_start=False, tracking_margin_max_m=0.0)
    runaways = 0
    for seed in (0, 2):
        least, fastest, farthest = _hover_by_a_wall(old, seed)
        runaways += fastest > 2.0 and (least < BODY_RADIUS_M or farthest > 5.0)
    assert runaways == 2


def test_straight_line_plans_start_from_their_reference():
    from planning.straight_line import straight_line_plan

    kw = dict(v_max_mps=0.6, a_max_mps2=0.6, yaw_rate_max_rps=0.4)
    goal = np.array([5.0, 0.0, 1.5])
    first = straight_line_plan(_state(0.0, [0.0, 0.0, 1.5]), goal, **kw)
    p_ref, v_ref = first.sample(0.1)[0:2]
    pushed = _state(0.1, p_ref + [0.0, 0.4, 0.0], v_ref + [0.0, 0.5, 0.0])
    r = straight_line_plan(pushed, goal, reference=first, **kw)
    np.testing.assert_allclose(r.p[0], p_ref, atol=1e-12)
    np.testing.assert_allclose(r.v[0], v_ref, atol=1e-12)
    # without a reference, beyond the reset distance or with a stale one: the measurement
    for ref, t, off in ((None, 0.1, 0.4), (first, 0.1, 1.6), (first, 0.7, 0.4)):
        s = _state(t, first.sample(t)[0] + [0.0, off, 0.0])
        np.testing.assert_allclose(straight_line_plan(s, goal, reference=ref, **kw).p[0], s.p, atol=1e-12)


def test_volume_drift_margin_grows_with_the_distance_flown_and_bounds_goal_and_plan():
    """The volume shrinks by ``volume_drift_fraction`` of the distance flown: a goal past the
    +x face is held that much farther inside after 6 m than at the start, and no knot enters
    the band."""
    cfg = PlannerConfig()
    assert cfg.volume_drift_fraction == 0.01
    volume = FlightVolume(np.array([-2.0, -5.0, 0.0]), np.array([8.0, 5.0, 4.0]))
    goal = np.array([12.0, 0.0, 1.5])  # outside the +x face
    planner = Planner(cfg)
    r = planner.step(_state(0.0, [0.0, 0.0, 1.5]), goal, OPEN, volume=volume)
    assert planner.drift_margin_m == 0.0
    assert r.goal_used[0] == pytest.approx(8.0 - cfg.body_radius_m, abs=1e-9)
    path = 0.0
    prev = np.array([0.0, 0.0, 1.5])
    for _ in range(150):  # perfect tracking: the vehicle is where the plan said
        t = r.trajectory.t0_s + 0.1
        p, v = r.trajectory.sample(t)[0:2]
        path += float(np.linalg.norm(p - prev))
        prev = p
        r = planner.step(_state(t, p, v), goal, OPEN, volume=volume)
    assert path > 6.0
    # counted in moves of at least 0.25 m along a straight path: short of the path by < 0.25 m
    assert 0.01 * (path - 0.25) - 1e-9 <= planner.drift_margin_m <= 0.01 * path + 1e-9
    assert r.goal_used[0] == pytest.approx(8.0 - cfg.body_radius_m - planner.drift_margin_m, abs=1e-9)
    assert r.trajectory.p[1:, 0].max() <= 8.0 - cfg.body_radius_m - planner.drift_margin_m + cfg.safety_tolerance_m
    planner.reset()
    assert planner.drift_margin_m == 0.0


def test_volume_drift_margin_ignores_hover_noise_and_can_be_switched_off():
    rng = np.random.default_rng(7)
    goal = np.array([0.0, 0.0, 1.5])
    planner = Planner(PlannerConfig())
    for k in range(300):  # 30 s of hover with 2 cm estimate noise (docs/realism.md): no path
        planner.step(_state(0.1 * k, goal + rng.normal(0.0, 0.02, 3)), goal, OPEN)
    assert planner.drift_margin_m == 0.0
    off = Planner(PlannerConfig(volume_drift_fraction=0.0))
    for k in range(30):
        off.step(_state(0.1 * k, [0.3 * k, 0.0, 1.5], [3.0, 0.0, 0.0]), np.array([20.0, 0.0, 1.5]), OPEN)
    assert off.drift_margin_m == 0.0
    capped = Planner(PlannerConfig(volume_drift_max_m=0.05))  # 8.7 m flown: 1 % would be 0.087 m
    for k in range(30):
        capped.step(_state(0.1 * k, [0.3 * k, 0.0, 1.5], [3.0, 0.0, 0.0]), np.array([20.0, 0.0, 1.5]), OPEN)
    assert capped.drift_margin_m == 0.05
    # goals chosen against the volume keep the safety distance and the drift margin
    assert capped.volume_goal_margin_m == pytest.approx(capped.config.d_safe_m + 0.05)
    with pytest.raises(PlannerConfigError, match="volume_drift_max_m"):
        PlannerConfig(volume_drift_max_m=-1.0)
    for bad in (-0.01, 0.5, float("nan")):
        with pytest.raises(PlannerConfigError, match="volume_drift_fraction"):
            PlannerConfig(volume_drift_fraction=bad)
