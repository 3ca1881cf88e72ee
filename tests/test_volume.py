import numpy as np
import pytest

from planning.volume import FlightVolume, FlightVolumeError


def test_contains_and_clamp_respect_margin():
    v = FlightVolume(np.array([0.0, -1.0, 0.0]), np.array([10.0, 1.0, 3.0]))
    assert v.contains([[5, 0, 1], [10.5, 0, 1]]).tolist() == [True, False]
    assert v.contains([9.9, 0, 1], margin_m=0.2).tolist() == [False]
    c = v.clamp(np.array([[12.0, 5.0, -1.0]]), margin_m=0.5)
    np.testing.assert_allclose(c, [[9.5, 0.5, 0.5]])
    assert bool(v.contains(c, margin_m=0.5 - 1e-9)[0])


def test_parse_round_trip_and_errors():
    v = FlightVolume.parse("-3, -4, 0, 5, 6, 4")
    assert v.to_list() == [-3.0, -4.0, 0.0, 5.0, 6.0, 4.0]
    assert FlightVolume.parse(",".join(map(str, v.to_list()))).to_list() == v.to_list()
    with pytest.raises(FlightVolumeError, match="six numbers"):
        FlightVolume.parse("1,2,3")
    with pytest.raises(FlightVolumeError, match="six numbers"):
        FlightVolume.parse("a,b,c,d,e,f")
    with pytest.raises(FlightVolumeError, match="min < max"):
        FlightVolume.parse("0,0,0,1,1,0")
    with pytest.raises(FlightVolumeError, match="finite"):
        FlightVolume(np.array([0, 0, np.nan]), np.ones(3))


def test_shrunk_never_inverts():
    v = FlightVolume(np.zeros(3), np.array([1.0, 1.0, 1.0])).shrunk(2.0)
    assert np.all(v.max_m > v.min_m)
    np.testing.assert_allclose(0.5 * (v.min_m + v.max_m), 0.5)
