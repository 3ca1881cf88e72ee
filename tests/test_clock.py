"""Clock: VLM calls are charged their modelled latency on one modelled inference engine, and
the vehicle flies on meanwhile."""

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
    clock = SimClock(latency=LatencyModel(single_engine=False))  # parallel engines: the old model
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


def test_two_calls_issued_together_finish_one_after_the_other():
    clock = SimClock()
    assert clock.latency.single_engine and clock.latency.priority_kinds == (DECISION,)
    d = clock.schedule(DECISION, "pixel (10, 20)")
    m = clock.schedule(MONITORING, "CONTINUE", prefix_reused=False)
    assert (d.start_s, d.done_s) == (0.0, pytest.approx(0.81))
    assert m.start_s == pytest.approx(0.81) and m.done_s == pytest.approx(0.81 + 1.98)
    assert m.wait_s == pytest.approx(0.81) and m.service_s == pytest.approx(1.98)
    delivered = {}
    for _ in range(30):
        t = round(clock.now_s + 0.1, 6)
        got = [c.result for c in clock.advance(0.1)]
        if got:
            delivered[t] = got
    assert delivered == {0.9: ["pixel (10, 20)"], 2.8: ["CONTINUE"]}
    assert clock.charged_s == {DECISION: pytest.approx(0.81), MONITORING: pytest.approx(1.98)}
    assert clock.waited_s == {DECISION: 0.0, MONITORING: pytest.approx(0.81)}


def test_decision_priority_jumps_the_queue_but_never_preempts():
    clock = SimClock()
    m1 = clock.schedule(MONITORING, "m1")  # runs 0 .. 1.15
    m2 = clock.schedule("decompose", "q", latency_s=2.0)  # waits: 1.15 .. 3.15
    clock.advance(0.5)
    d = clock.schedule(DECISION, "d")  # served before the waiting call, after the running one
    by_id = {c.call_id: c for c in clock.pending()}
    assert by_id[m1.call_id].done_s == pytest.approx(1.15)
    assert (d.start_s, d.done_s) == (pytest.approx(1.15), pytest.approx(1.96))
    assert (by_id[m2.call_id].start_s, by_id[m2.call_id].done_s) == (pytest.approx(1.96), pytest.approx(3.96))
    # plain FIFO: the decision waits its turn
    fifo = SimClock(latency=LatencyModel(priority_kinds=()))
    fifo.schedule(MONITORING, "m1")
    fifo.schedule("decompose", "q", latency_s=2.0)
    fifo.advance(0.5)
    assert fifo.schedule(DECISION, "d").done_s == pytest.approx(1.15 + 2.0 + 0.81)


def test_cancelling_the_running_call_frees_the_engine_at_once():
    clock = SimClock()
    a = clock.schedule(MONITORING, "a")  # 0 .. 1.15
    b = clock.schedule(DECISION, "b")  # 1.15 .. 1.96
    clock.advance(0.4)
    assert clock.cancel(a.call_id)
    (b_now,) = clock.pending()
    assert b_now.call_id == b.call_id and b_now.done_s == pytest.approx(0.4 + 0.81)
    assert [c.result for c in clock.advance(0.81)] == ["b"]
    # the engine idle since 1.21: a new call starts at once
    assert clock.schedule(DECISION, "c").done_s == pytest.approx(clock.now_s + 0.81)


def test_a_call_learnt_of_late_is_placed_at_its_submission_time():
    clock = SimClock(t0_s=5.0)
    clock.advance(0.3)
    c = clock.schedule(DECISION, "d", submitted_s=5.1)
    assert (c.start_s, c.done_s) == (pytest.approx(5.1), pytest.approx(5.91))
    with pytest.raises(ClockError, match="submitted_s must be finite and not after now"):
        clock.schedule(DECISION, "d", submitted_s=6.0)


@pytest.mark.parametrize(
    "kw, message",
    [({"decision_s": -1.0}, "decision_s"), ({"single_engine": "yes"}, "single_engine"), ({"priority_kinds": "decision"}, "priority_kinds")],
)
def test_latency_model_rejects_bad_fields(kw, message):
    with pytest.raises(ValueError, match=message):
        LatencyModel(**kw)


def test_latency_precedence_explicit_then_response_then_model():
    clock = SimClock(t0_s=10.0, latency=LatencyModel(single_engine=False))
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
