"""Agent runtimes: ClockRuntime lands calls after their modelled latency on the virtual clock;
ThreadRuntime lands them when their thread finishes, or (honour_modelled_latency) no earlier
than the modelled engine (one queue by default) serves them on its own clock."""

import threading
from dataclasses import dataclass

import pytest

from onfly.runtime import ClockRuntime, ThreadRuntime
from onfly.world.clock import LatencyModel, SimClock


@dataclass(frozen=True)
class Answer:
    text: str
    latency_s: float


class FakeClock:
    """A clock the test moves by hand (seconds)."""

    def __init__(self, t_s: float = 100.0) -> None:
        self.t_s = t_s

    def __call__(self) -> float:
        return self.t_s


def finished(rt: ThreadRuntime, kind: str) -> None:
    assert rt.wait_finished(kind, 5.0), f"{kind} call did not finish"


def test_thread_runtime_default_lands_as_soon_as_the_thread_finishes():
    clock = FakeClock()
    rt = ThreadRuntime(clock)
    rt.submit("decision", lambda: Answer("a", 0.81))
    finished(rt, "decision")
    landed = rt.poll()
    assert [(x.kind, x.outcome.text, x.submitted_s, x.landed_s) for x in landed] == [("decision", "a", 100.0, 100.0)]
    assert not rt.busy("decision") and rt.poll() == []
    rt.close()


def test_honoured_latency_lands_at_submit_plus_latency_and_stays_busy_until_then():
    """Parallel engines (the old model): each call lands at its submission plus its latency."""
    clock = FakeClock()
    rt = ThreadRuntime(clock, honour_modelled_latency=True, latency=LatencyModel(single_engine=False))
    rt.submit("decision", lambda: Answer("d", 0.81))
    clock.t_s = 100.5
    rt.submit("monitoring", lambda: Answer("m", 1.15))
    finished(rt, "decision")
    finished(rt, "monitoring")
    clock.t_s = 100.8
    assert rt.poll() == [] and rt.busy("decision") and rt.busy("monitoring")
    with pytest.raises(RuntimeError, match="a decision call is already running"):
        rt.submit("decision", lambda: Answer("again", 0.0))
    clock.t_s = 100.81
    landed = rt.poll()
    assert [(x.kind, x.landed_s) for x in landed] == [("decision", 100.81)]
    assert not rt.busy("decision") and rt.busy("monitoring")
    clock.t_s = 101.64
    assert rt.poll() == []
    clock.t_s = 101.65
    landed = rt.poll()
    assert [(x.kind, x.outcome.text, x.submitted_s) for x in landed] == [("monitoring", "m", 100.5)]
    rt.close()


def test_honoured_latency_on_one_engine_serves_calls_one_after_the_other():
    """Default engine model: monitoring submitted while the decision runs waits for it, and a
    decision submitted while monitoring waits is served first (decision priority)."""
    clock = FakeClock()
    rt = ThreadRuntime(clock, honour_modelled_latency=True)
    rt.submit("monitoring", lambda: Answer("m1", 1.15))
    finished(rt, "monitoring")
    assert rt.poll() == []  # scheduled at 100.0, served until 101.15
    clock.t_s = 100.2
    rt.submit("decision", lambda: Answer("d", 0.81))
    rt.submit("x", lambda: Answer("x", 0.5))
    finished(rt, "decision")
    finished(rt, "x")
    clock.t_s = 100.3
    assert rt.poll() == []
    clock.t_s = 101.1
    assert rt.poll() == [] and rt.busy("monitoring")
    clock.t_s = 101.15
    assert [(x.kind, x.submitted_s) for x in rt.poll()] == [("monitoring", 100.0)]
    clock.t_s = 101.95
    assert rt.poll() == []
    clock.t_s = 101.96  # decision served 101.15 .. 101.96
    assert [x.kind for x in rt.poll()] == ["decision"]
    clock.t_s = 102.46  # then x, 101.96 .. 102.46
    assert [x.kind for x in rt.poll()] == ["x"] and not rt.busy("x")
    rt.close()


def test_honoured_latency_never_lands_before_the_thread_finishes():
    clock = FakeClock()
    release = threading.Event()
    rt = ThreadRuntime(clock, honour_modelled_latency=True)

    def slow():
        release.wait(5.0)
        return Answer("late", 0.1)

    rt.submit("decision", slow)
    clock.t_s = 110.0  # far past the modelled latency, but the call is still computing
    assert rt.poll() == [] and rt.busy("decision")
    release.set()
    finished(rt, "decision")
    assert [x.outcome.text for x in rt.poll()] == ["late"]
    rt.close()


@pytest.mark.parametrize("outcome", [object(), Answer("neg", -1.0), Answer("nan", float("nan")), Answer("inf", float("inf"))])
def test_honoured_latency_without_a_usable_latency_lands_at_once(outcome):
    clock = FakeClock()
    rt = ThreadRuntime(clock, honour_modelled_latency=True)
    rt.submit("decision", lambda: outcome)
    finished(rt, "decision")
    landed = rt.poll()
    assert len(landed) == 1 and landed[0].outcome is outcome
    rt.close()


def test_a_call_that_raises_lands_at_once_as_its_exception():
    clock = FakeClock()
    rt = ThreadRuntime(clock, honour_modelled_latency=True)

    def boom():
        raise ConnectionError("VLM server gone")

    rt.submit("decision", boom)
    finished(rt, "decision")
    landed = rt.poll()
    assert len(landed) == 1 and isinstance(landed[0].outcome, ConnectionError)
    assert str(landed[0].outcome) == "VLM server gone" and not rt.busy("decision")
    rt.close()


def test_wait_finished_without_a_call_and_on_a_timeout():
    rt = ThreadRuntime(FakeClock())
    assert rt.wait_finished("decision", 0.0)
    gate = threading.Event()
    rt.submit("decision", lambda: gate.wait(5.0))
    assert not rt.wait_finished("decision", 0.05)
    gate.set()
    assert rt.wait_finished("decision", 5.0)
    rt.close()


def test_clock_runtime_charges_the_same_latency_on_the_virtual_clock():
    """The reference the honoured thread runtime reproduces in wall time."""
    rt = ClockRuntime(SimClock(0.0))
    rt.submit("decision", lambda: Answer("d", 0.81))
    rt.advance(0.8)
    assert rt.poll() == [] and rt.busy("decision")
    rt.advance(0.01)
    landed = rt.poll()
    assert [(x.kind, x.submitted_s, x.landed_s) for x in landed] == [("decision", 0.0, pytest.approx(0.81))]


def test_clock_runtime_queues_calls_on_one_engine():
    """Two calls issued together land one after the other on the virtual clock."""
    rt = ClockRuntime(SimClock(0.0))
    rt.submit("decision", lambda: Answer("d", 0.81))
    rt.submit("monitoring", lambda: Answer("m", 1.15))
    rt.advance(0.81)
    assert [x.kind for x in rt.poll()] == ["decision"] and rt.busy("monitoring")
    rt.advance(1.14)
    assert rt.poll() == []
    rt.advance(0.01)
    landed = rt.poll()
    assert [(x.kind, x.submitted_s, x.landed_s) for x in landed] == [("monitoring", 0.0, pytest.approx(1.96))]
