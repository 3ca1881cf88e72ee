"""TypeFly-style baseline: skill programs over the detector, no map, stops only by its skill."""

from __future__ import annotations

import math

import numpy as np
import pytest

from baseline_harness import RecordingVlm, fly, text
from onfly.baselines.common import FlightLimits
from onfly.baselines.typefly import ProgramError, Skill, TypeflyConfig, TypeflyMethod, make_typefly, parse_program
from onfly.bench.registry import get_factory
from planning.esdf import EsdfMap
from planning.planner import Planner
from planning.planner_config import PlannerConfig
from vlm.prompts import TypeflyPrompt

LIMITS = FlightLimits.from_planner(PlannerConfig())
PERFECT_DETECTOR = {"miss_prob": 0.0, "miss_prob_small": 0.0, "false_positive_prob": 0.0}


def method(backend, **cfg) -> TypeflyMethod:
    return TypeflyMethod("sim:perfect", TypeflyConfig(detector=PERFECT_DETECTOR, **cfg), LIMITS, backend=backend)


def test_parse_program_reads_the_skill_language():
    assert parse_program("find red van; approach red van ;stop") == [Skill("find", "red van"), Skill("approach", "red van"), Skill("stop")]
    assert parse_program("```\nturn -45\nmove_forward 2.5\n```") == [Skill("turn", -45.0), Skill("move_forward", 2.5)]
    assert parse_program("Program: STOP") == [Skill("stop")]
    assert Skill("move_forward", 3.0).text() == "move_forward 3" and Skill("find", "the van").text() == "find the van"


@pytest.mark.parametrize(
    "bad, match",
    [
        ("", "empty program"),
        ("fly_to target; stop", "unknown skill 'fly_to target'"),
        ("approach", "unknown skill 'approach'"),
        ("move_forward 9", r"outside \(0, 5\] metres"),
        ("move_forward -1", "outside"),
        ("turn 400", r"outside \[-360, 360\]"),
        ("stop; stop; stop; stop; stop; stop", "6 skills, more than 5"),
    ],
)
def test_parse_program_rejects_bad_programs(bad, match):
    with pytest.raises(ProgramError, match=match):
        parse_program(bad)


def test_flies_to_the_target_and_stops_through_its_skill():
    vlm = RecordingVlm("perfect")
    m = method(vlm)
    res, steps = fly(m, "park-o01", time_limit_s=30.0)
    assert res.end_reason == "stopped" and res.metrics.success and not res.metrics.collided
    assert m.history[-1] == "stop" and m.history[:-1] == ["approach green bench: done"] * (len(m.history) - 1)
    # every call was a TypeFly planning prompt over the detector's scene description
    assert all(isinstance(p, TypeflyPrompt) for p, _, _ in vlm.calls)
    assert vlm.calls[-1][2].text == "stop"
    # the episode ended at the first step whose program reached the stop skill
    assert res.trace.stopped_by_method and not any(s.output.done for s in steps)


def test_never_stops_without_the_stop_skill():
    # the same flight with every "stop" program replaced: the vehicle reaches the van, hovers
    # and the episode runs into its time limit
    vlm = RecordingVlm("perfect", override=lambda p, i, r: text("turn 0") if r.text == "stop" else None)
    m = method(vlm)
    res, steps = fly(m, "park-o01", time_limit_s=30.0)
    assert res.end_reason == "time_limit" and res.metrics.oracle_success and not res.metrics.success
    assert not any(s.output.done for s in steps) and "stop" not in m.history


def test_find_turns_left_in_45_degree_steps_then_reports_not_found():
    programs = iter(["find purple elephant"])
    vlm = RecordingVlm("perfect", override=lambda p, i, r: text(next(programs, "turn 0")))
    m = method(vlm)
    res, steps = fly(m, "urban_block-o01", time_limit_s=32.0)
    assert "find purple elephant: not found" in m.history
    yaws = np.unwrap([s.state.yaw for s in steps])
    turned = yaws - yaws[0]
    assert turned.max() == pytest.approx(7 * math.pi / 4, abs=0.06)  # 7 turns of 45 deg, then the 8th check fails
    assert turned.min() > -0.05  # always left
    # the vehicle never translated while searching
    xy = np.array([s.state.p[:2] for s in steps])
    assert np.max(np.linalg.norm(xy - xy[0], axis=1)) < 0.05


def test_unreadable_programs_are_asked_again_and_never_stop():
    vlm = RecordingVlm("perfect", override=lambda p, i, r: text("I will fly toward the target now."))
    m = method(vlm)
    res, steps = fly(m, "urban_block-o01", time_limit_s=6.0)
    assert res.end_reason == "time_limit"
    summary = m.summary()
    # every landed answer was rejected (the last call may still be in flight at the limit)
    assert summary["plans"] == len(vlm.calls) >= 5
    assert summary["program_rejected"] in (len(vlm.calls), len(vlm.calls) - 1) and m.programs == []
    xy = np.array([s.state.p[:2] for s in steps])
    assert np.max(np.linalg.norm(xy - xy[0], axis=1)) < 0.05  # hovered while asking


def test_holds_no_map_and_no_planner():
    m = method(RecordingVlm("perfect"))
    fly(m, "urban_block-o01", time_limit_s=3.0)
    assert not any(isinstance(v, (EsdfMap, Planner)) for v in vars(m).values())


def test_factory_options_and_registry():
    m = make_typefly("sim:nominal", 3, planner={"v_max_mps": 0.5}, verifier={}, approach_step_m=2.0, detector={"miss_prob": 0.2})
    assert m.limits.v_max_mps == 0.5 and m.config.approach_step_m == 2.0 and m._detector_config.miss_prob == 0.2
    assert get_factory("typefly") is make_typefly
    with pytest.raises(ValueError, match="unknown typefly option"):
        make_typefly("sim:nominal", 0, step_m=1.0)
    with pytest.raises(ValueError, match="unknown detector option"):
        make_typefly("sim:nominal", 0, detector={"recall": 0.5})
    with pytest.raises(ValueError, match="approach_step_m must be a finite number > 0"):
        make_typefly("sim:nominal", 0, approach_step_m=0.0)
