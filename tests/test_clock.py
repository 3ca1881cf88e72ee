"""Clock: VLM calls are charged their modelled latency and the vehicle flies on meanwhile."""

from __future__ import annotations

import numpy as np
import pytest

from onfly.world.clock import DECISION, MONITORING, ClockError, LatencyModel, SimClock
from onfly.world.scene import parse_scene
from onfly.world.world import World
from planning.trajectory import Trajectory, VehicleState
from vlm.types import CallStatus, VlmResponse


def test_default_latencies_are_the_papers():
    m = LatencyModel()
    assert m.latency_s(DECISION) == 0.81
    assert m.latency_s(MONITORING, prefix_reused=True) == 1.15
    assert m.latency_s(MONITORING, prefix_reused=False) == 1.98
    with pytest.raises(ClockError, match="no modelled latency for call kind 'decompose'"):
        m.latency_s("decompose")


def test_results_are_delivered_only_when_time_reaches_completion():
    clock = SimClock()
    d = clock.schedule(DECISION, "pixel (10, 20)")
    m = clock.schedule(MONITORING, "CONTINUE", prefix_reused=False)
    assert d.done_s == pytest.approx(0.81) and m.done_s == pytest.approx(1.98)
    delivered = []
    for _ in range(25):
        delivered.append((round(clock.now_s + 0.1, 6), [c.result for c in clock.advance(0.1)]))
    got = {t: r for t, r in delivered if r}
    assert got == {0.9: ["pixel (10, 20)"], 2.0: ["CONTINUE"]}
    assert clock.pending() == ()
    assert clock.charged_s == {DECISION: pytest.approx(0.81), MONITORING: pytest.approx(1.98)}
    assert clock.call_counts == {DECISION: 1, MONITORING: 1}


def test_latency_precedence_explicit_then_response_then_model():
    clock = SimClock(t0_s=10.0)
    resp = VlmResponse(CallStatus.OK, "STOP", latency_s=0.42)
    assert clock.schedule(MONITORING, resp).latency_s == pytest.approx(0.42)
    assert clock.schedule(MONITORING, resp, latency_s=2.5).latency_s == pytest.approx(2.5)
    zero = VlmResponse(CallStatus.OK, "STOP", latency_s=0.0)
    assert clock.schedule(MONITORING, zero).latency_s == pytest.approx(1.15)
    assert clock.schedule("decompose", "x", latency_s=3.0).done_s == pytest.approx(13.0)
    with pytest.raises(ClockError, match="latency_s must be finite"):
        clock.schedule(DECISION, "x", latency_s=-1.0)
    with pytest.raises(ClockError, match="dt_s must be finite"):
        clock.advance(-0.1)


def test_same_completion_time_keeps_submission_order_and_cancel_drops():
    clock = SimClock()
    a = clock.schedule("x", "a", latency_s=0.5)
    b = clock.schedule("x", "b", latency_s=0.5)
    c = clock.schedule("x", "c", latency_s=0.3)
    assert clock.busy("x") and not clock.busy(DECISION)
    assert clock.cancel(c.call_id) and not clock.cancel(c.call_id)
    assert [p.result for p in clock.advance(1.0)] == ["a", "b"]
    assert a.call_id < b.call_id


def test_vehicle_keeps_flying_the_last_plan_while_a_call_is_pending():
    scene = parse_scene(
        {
            "format": "onfly-scene/1",
            "name": "open",
            "bounds": {"min_m": [-50, -50, 0], "max_m": [50, 50, 10]},
            "start": {"position_m": [0, 0, 1.5], "yaw_deg": 0},
            "objects": [{"name": "ground", "label": "ground", "instance_id": 1, "color": "#707070",
                         "parts": [{"type": "plane", "center_m": [0, 0, 0], "size_m": [100, 100]}]}],
        }
    )
    world = World(scene, initial_state=VehicleState(0.0, [0, 0, 1.5], [0.5, 0, 0], 0.0))
    n, dt = 100, 0.1
    p = np.zeros((n + 1, 3))
    p[:, 0] = 0.5 * dt * np.arange(n + 1)
    p[:, 2] = 1.5
    world.set_trajectory(Trajectory(0.0, dt, p, np.tile([0.5, 0, 0], (n + 1, 1)), np.zeros(n + 1), np.zeros((n, 3)), np.zeros(n)))
    call = world.clock.schedule(DECISION, "new goal")
    xs = []
    for _ in range(8):
        step = world.step(0.1)
        assert step.completed == ()
        xs.append(step.state.p[0])
    assert world.clock.busy(DECISION)
    np.testing.assert_allclose(np.diff(xs), 0.05, atol=1e-9)  # flying at 0.5 m/s during the call
    step = world.step(0.1)
    assert [c.result for c in step.completed] == ["new goal"] and step.completed[0] is call
    assert world.clock.now_s == pytest.approx(0.9) and step.state.t_s == pytest.approx(0.9)
    assert step.state.p[0] == pytest.approx(0.45, abs=1e-9)
