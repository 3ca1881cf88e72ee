"""Truncated exact EDT against scipy's exact transform."""

import numpy as np
import pytest
import scipy.ndimage as ndi
from hypothesis import given, settings
from hypothesis import strategies as st

from planning.esdf_edt import EdtError, edt_dtype, truncated_squared_edt


def _reference(mask: np.ndarray, k: int) -> np.ndarray:
    """scipy's exact squared EDT to the True voxels, capped at k^2 + 1."""
    if not mask.any():
        return np.full(mask.shape, k * k + 1)
    d2 = ndi.distance_transform_edt(~mask) ** 2
    return np.where(d2 <= k * k, np.rint(d2), k * k + 1).astype(np.int64)


@pytest.mark.parametrize("k", [1, 3, 10, 11, 12, 25])
@pytest.mark.parametrize("shape", [(40,), (23, 31), (30, 27, 19)])
def test_matches_scipy_exactly_within_clamp(k, shape):
    rng = np.random.default_rng(k * 100 + len(shape))
    mask = rng.random(shape) < 0.02
    got = truncated_squared_edt(mask, k)
    assert got.shape == mask.shape
    assert got.dtype == (np.uint8 if k <= 11 else np.uint16)
    np.testing.assert_array_equal(got.astype(np.int64), _reference(mask, k))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    k=st.integers(1, 14),
    density=st.floats(0.0, 0.3),
    shape=st.tuples(st.integers(1, 14), st.integers(1, 14), st.integers(1, 14)),
)
def test_property_random_masks(seed, k, density, shape):
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) < density
    np.testing.assert_array_equal(truncated_squared_edt(mask, k).astype(np.int64), _reference(mask, k))


def test_region_equals_crop_of_full_transform():
    rng = np.random.default_rng(3)
    mask = rng.random((35, 28, 22)) < 0.01
    full = truncated_squared_edt(mask, 7)
    lo, hi = (5, 0, 9), (30, 11, 22)
    part = truncated_squared_edt(mask, 7, region=(lo, hi))
    np.testing.assert_array_equal(part, full[5:30, 0:11, 9:22])


def test_empty_mask_is_all_cap_and_full_mask_is_zero():
    assert np.all(truncated_squared_edt(np.zeros((5, 6, 7), bool), 4) == 17)
    assert np.all(truncated_squared_edt(np.ones((5, 6, 7), bool), 4) == 0)


def test_single_site_gives_exact_integer_squares():
    mask = np.zeros((21, 21, 21), bool)
    mask[10, 10, 10] = True
    d2 = truncated_squared_edt(mask, 6).astype(int)
    i, j, k = np.indices(mask.shape) - 10
    true = i * i + j * j + k * k
    np.testing.assert_array_equal(d2, np.where(true <= 36, true, 37))


def test_bad_inputs_raise():
    with pytest.raises(EdtError, match="bool"):
        truncated_squared_edt(np.zeros((3, 3)), 2)
    with pytest.raises(EdtError, match="k_max must be >= 1"):
        truncated_squared_edt(np.zeros((3, 3), bool), 0)
    with pytest.raises(EdtError, match="<= 180"):
        edt_dtype(181)
    with pytest.raises(EdtError, match="non-empty"):
        truncated_squared_edt(np.zeros((0, 3), bool), 2)
    with pytest.raises(EdtError, match="region"):
        truncated_squared_edt(np.zeros((4, 4), bool), 2, region=((0, 3), (4, 3)))
