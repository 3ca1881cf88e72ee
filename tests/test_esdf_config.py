"""EsdfConfig: defaults, derived sizes and validation naming the field."""

import dataclasses

import pytest

from planning.esdf_config import EsdfConfig, EsdfConfigError


def test_defaults_follow_the_issue_and_the_paper():
    cfg = EsdfConfig()
    assert cfg.voxel_m == 0.1
    assert cfg.size_m == (16.0, 16.0, 5.0)
    assert cfg.grid_shape == (160, 160, 50)
    assert cfg.max_range_m == 7.0
    # the window covers D_max plus a margin on every horizontal side of the vehicle
    assert min(cfg.size_m[:2]) / 2 >= cfg.max_range_m + 0.5
    # safe for a real depth camera: unknown is an obstacle, holes clear a bounded stretch
    assert cfg.unknown_policy == "occupied"
    assert cfg.no_reading_clear_m == 4.5 and cfg.body_clear_radius_m == 1.2
    # the clamp reaches every clearance the default planner reads (d_safe + margin + goal margin)
    assert cfg.max_distance_voxels == 16
    assert not cfg.body_clear_in_view
    # inside depth is (d_in - 1) voxels, so the transform needs one voxel more than 0.5 m
    assert cfg.max_inside_voxels == 6


def test_derived_sizes_round_sensibly():
    cfg = EsdfConfig(voxel_m=0.15, size_m=(3.0, 2.0, 1.0), max_distance_m=0.5)
    assert cfg.grid_shape == (20, 13, 7)
    assert cfg.max_distance_voxels == 4  # ceil(0.5 / 0.15): every distance <= 0.5 m is exact


def test_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        EsdfConfig().voxel_m = 0.2


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("voxel_m", 0.0, "voxel_m must be a positive"),
        ("voxel_m", float("nan"), "voxel_m must be a positive"),
        ("max_range_m", -1.0, "max_range_m must be a positive"),
        ("max_distance_m", 0.0, "max_distance_m must be a positive"),
        ("max_distance_m", 50.0, "max_distance_m must be at most 180 voxels"),
        ("max_inside_distance_m", -0.1, "max_inside_distance_m must be a positive"),
        ("min_range_m", -0.1, "min_range_m must be a finite number >= 0"),
        ("min_range_m", 8.0, "min_range_m .* must be smaller than max_range_m"),
        ("clear_margin_m", float("inf"), "clear_margin_m must be a finite"),
        ("surface_thickness_m", -0.2, "surface_thickness_m must be"),
        ("size_m", (1.0, 2.0), "size_m must be three"),
        ("size_m", (1.0, 2.0, 0.1), "size_m must be at least two voxels"),
        ("stride_px", 0, "stride_px must be an integer >= 1"),
        ("stride_px", 1.5, "stride_px must be an integer >= 1"),
        ("miss_logodds", 0.3, "miss_logodds must be negative"),
        ("hit_logodds", -1.0, "hit_logodds must be a positive"),
        ("occupied_logodds", 3.0, "min_logodds < occupied_logodds < max_logodds"),
        ("unknown_policy", "maybe", "unknown_policy must be one of"),
        ("no_reading_clear_m", -1.0, "no_reading_clear_m must be a finite number >= 0"),
        ("body_clear_radius_m", float("nan"), "body_clear_radius_m must be a finite number >= 0"),
    ],
)
def test_invalid_fields_raise_naming_the_field(field, value, message):
    with pytest.raises(EsdfConfigError, match=message):
        EsdfConfig(**{field: value})


def test_first_hit_must_be_able_to_occupy():
    with pytest.raises(EsdfConfigError, match="hit_logodds .* must exceed occupied_logodds"):
        EsdfConfig(hit_logodds=0.3, occupied_logodds=0.5)


def test_config_error_is_a_value_error():
    assert issubclass(EsdfConfigError, ValueError)
