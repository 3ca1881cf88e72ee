"""PlannerConfig: paper defaults, validation naming the field, TOML and dict round trips."""

from __future__ import annotations

import dataclasses

import pytest

from planning.planner_config import PlannerConfig, PlannerConfigError


def test_defaults_are_the_paper_limits_and_documented_choices():
    c = PlannerConfig()
    assert (c.v_max_mps, c.a_max_mps2, c.yaw_rate_max_rps) == (0.6, 0.6, 0.4)
    assert c.horizon_steps == 40 and c.dt_s == 0.1
    assert c.horizon_s == pytest.approx(4.0)
    # 0.25 m body radius + the paper's 0.2 m clearance dilation
    assert c.d_safe_m == pytest.approx(0.45)
    # stopping from v_max at a_max takes 1 s = 10 intervals, plus the knot itself
    assert c.braking_steps == 11


def test_config_is_frozen():
    c = PlannerConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.v_max_mps = 1.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("v_max_mps", -0.1, "v_max_mps must be > 0"),
        ("a_max_mps2", 0.0, "a_max_mps2 must be > 0"),
        ("d_safe_m", float("nan"), "d_safe_m must be finite"),
        ("w_yaw", -1.0, "w_yaw must be >= 0"),
        ("horizon_steps", 1, "horizon_steps must be >= 2"),
        ("horizon_steps", 40.0, "horizon_steps must be an int"),
        ("qp_polish", 1, "qp_polish must be a bool"),
        ("w_goal", True, "w_goal must be a number"),
        ("speed_tolerance_rel", 0.5, "speed_tolerance_rel must be <= 0.1"),
        ("speed_cuts_per_knot", 0, "speed_cuts_per_knot must be >= 1"),
    ],
)
def test_invalid_fields_raise_naming_the_field(field, value, match):
    with pytest.raises(PlannerConfigError, match=match):
        PlannerConfig(**{field: value})


def test_config_error_is_a_value_error():
    assert issubclass(PlannerConfigError, ValueError)


def test_ints_given_for_floats_are_coerced():
    c = PlannerConfig(v_max_mps=1, w_goal=2)
    assert isinstance(c.v_max_mps, float) and c.v_max_mps == 1.0
    assert isinstance(c.w_goal, float)


def test_dict_round_trip():
    c = PlannerConfig(v_max_mps=0.8, horizon_steps=30, w_yaw=5.0)
    assert PlannerConfig.from_dict(c.to_dict()) == c


def test_from_dict_rejects_unknown_fields_and_lists_valid_ones():
    with pytest.raises(PlannerConfigError, match=r"unknown planner config field\(s\) \['vmax'\].*v_max_mps"):
        PlannerConfig.from_dict({"vmax": 1.0})


def test_from_toml_reads_the_planner_table(tmp_path):
    path = tmp_path / "cfg.toml"
    path.write_text("[planner]\nv_max_mps = 0.9\nhorizon_steps = 20\n\n[other]\nx = 1\n")
    c = PlannerConfig.from_toml(path)
    assert c.v_max_mps == 0.9 and c.horizon_steps == 20
    assert c.a_max_mps2 == PlannerConfig().a_max_mps2


def test_from_toml_top_level_and_errors_name_the_file(tmp_path):
    path = tmp_path / "flat.toml"
    path.write_text("w_goal = 3.0\n")
    assert PlannerConfig.from_toml(path).w_goal == 3.0
    bad = tmp_path / "bad.toml"
    bad.write_text("[planner]\nv_max_mps = -1.0\n")
    with pytest.raises(PlannerConfigError, match=r"bad\.toml.*v_max_mps must be > 0"):
        PlannerConfig.from_toml(bad)
    with pytest.raises(PlannerConfigError, match="cannot read planner config"):
        PlannerConfig.from_toml(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[planner\n")
    with pytest.raises(PlannerConfigError, match="cannot read planner config"):
        PlannerConfig.from_toml(broken)


def test_the_default_map_shows_every_clearance_the_default_planner_asks_for():
    """EsdfConfig's clamp must exceed d_safe + the largest tracking margin + the goal/guide
    margin: with the old 1.0 m clamp a 0.6 m margin left no point of any map clear enough."""
    from planning.esdf_config import EsdfConfig
    from planning.planner_config import check_field_reach

    cfg = PlannerConfig()
    assert cfg.field_reach_m == pytest.approx(0.45 + 1.0 + 0.1)
    check_field_reach(cfg, EsdfConfig().max_distance_m)  # no error
    with pytest.raises(PlannerConfigError, match="max_distance_m"):
        check_field_reach(cfg, 1.0)
    check_field_reach(dataclasses.replace(cfg, tracking_margin_max_m=0.4), 1.0)


def test_a_pilot_whose_map_is_clamped_below_the_planners_reach_is_refused():
    from onfly.pilot import PilotConfig, PilotConfigError
    from planning.esdf_config import EsdfConfig

    with pytest.raises(PilotConfigError, match="max_distance_m"):
        PilotConfig(esdf=EsdfConfig(max_distance_m=1.0))
