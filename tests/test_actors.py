"""Actor motions: poses at any time against hand-computed values, and the motion table parser."""

import math

import numpy as np
import pytest

from onfly.world.actors import (
    CircleMotion,
    MotionFormatError,
    PathMotion,
    Waypoint,
    parse_motion,
    pose_at,
    poses_at,
    positions_at,
)


def _square_path(loop=True, start_s=0.0):
    # (0,0) -> (4,0) at 1 m/s [4 s], pause 1 s at (4,0); -> (4,3) at 2 m/s [1.5 s];
    # -> back to (0,0) at 1 m/s [5 s] (loop) ; cycle 11.5 s
    return PathMotion(
        (Waypoint((0, 0, 0), 1.0), Waypoint((4, 0, 0), 2.0, pause_s=1.0), Waypoint((4, 3, 0), 1.0)),
        loop=loop,
        start_s=start_s,
    )


def test_path_segment_interpolation():
    m = _square_path()
    p = pose_at(m, 2.5)
    np.testing.assert_allclose(p.position_m, [2.5, 0.0, 0.0])
    np.testing.assert_allclose(p.velocity_mps, [1.0, 0.0, 0.0])
    assert p.yaw_rad == pytest.approx(0.0)
    assert p.moving
    # second segment, at 2 m/s north, 0.5 s in
    p = pose_at(m, 5.5)
    np.testing.assert_allclose(p.position_m, [4.0, 1.0, 0.0])
    np.testing.assert_allclose(p.velocity_mps, [0.0, 2.0, 0.0])
    assert p.yaw_rad == pytest.approx(math.pi / 2)
    # closing segment (4,3) -> (0,0): direction (-0.8, -0.6), 2 s in
    p = pose_at(m, 8.5)
    np.testing.assert_allclose(p.position_m, [4.0 - 1.6, 3.0 - 1.2, 0.0])
    np.testing.assert_allclose(p.velocity_mps, [-0.8, -0.6, 0.0])
    assert p.yaw_rad == pytest.approx(math.atan2(-0.6, -0.8))


def test_path_pause_holds_position_and_heading():
    m = _square_path()
    for t in (4.0, 4.3, 4.999):
        p = pose_at(m, t)
        np.testing.assert_allclose(p.position_m, [4.0, 0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(p.velocity_mps, 0.0)
        assert not p.moving
        assert p.yaw_rad == pytest.approx(0.0)  # heading of the segment just walked
    p = pose_at(m, 5.0)
    assert p.moving and p.yaw_rad == pytest.approx(math.pi / 2)


def test_path_loop_wraps():
    m = _square_path()
    assert m.cycle_s == pytest.approx(11.5)
    assert m.length_m == pytest.approx(12.0)
    for t in (0.7, 5.2, 9.9):
        np.testing.assert_allclose(pose_at(m, t + 3 * m.cycle_s).position_m, pose_at(m, t).position_m, atol=1e-9)
    np.testing.assert_allclose(pose_at(m, 11.5).position_m, [0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pose_at(m, 12.0).position_m, [0.5, 0.0, 0.0])


def test_path_one_way_stops_at_the_end():
    m = _square_path(loop=False)
    assert m.cycle_s == pytest.approx(6.5)  # 4 + pause 1 + 1.5
    p = pose_at(m, 6.0)
    np.testing.assert_allclose(p.position_m, [4.0, 2.0, 0.0])
    for t in (6.5, 7.0, 1000.0):
        p = pose_at(m, t)
        np.testing.assert_allclose(p.position_m, [4.0, 3.0, 0.0])
        assert not p.moving
        np.testing.assert_allclose(p.velocity_mps, 0.0)
        assert p.yaw_rad == pytest.approx(math.pi / 2)


def test_path_before_start_stands_at_first_waypoint():
    m = _square_path(start_s=3.0)
    p = pose_at(m, 1.0)
    np.testing.assert_allclose(p.position_m, [0.0, 0.0, 0.0])
    assert not p.moving and p.yaw_rad == pytest.approx(0.0)
    np.testing.assert_allclose(pose_at(m, 4.5).position_m, [1.5, 0.0, 0.0])


def test_path_vertical_segment_keeps_heading_and_climbs():
    m = PathMotion((Waypoint((0, 0, 0), 1.0), Waypoint((2, 0, 0), 0.5), Waypoint((2, 0, 1), 1.0)), loop=False)
    p = pose_at(m, 3.0)  # 1 s into the climb at 0.5 m/s
    np.testing.assert_allclose(p.position_m, [2.0, 0.0, 0.5])
    np.testing.assert_allclose(p.velocity_mps, [0.0, 0.0, 0.5])
    assert p.yaw_rad == pytest.approx(0.0)


def test_circle_phase_and_direction():
    ccw = CircleMotion((1.0, 2.0, 0.0), radius_m=2.0, speed_mps=1.0, phase_rad=math.pi / 2)
    p = pose_at(ccw, 0.0)
    np.testing.assert_allclose(p.position_m, [1.0, 4.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(p.velocity_mps, [-1.0, 0.0, 0.0], atol=1e-12)
    assert p.yaw_rad == pytest.approx(math.pi)
    # a quarter lap (pi * r / 2 = pi metres at 1 m/s) later: west of the centre
    p = pose_at(ccw, math.pi)
    np.testing.assert_allclose(p.position_m, [-1.0, 2.0, 0.0], atol=1e-12)
    assert p.yaw_rad == pytest.approx(-math.pi / 2)
    cw = CircleMotion((1.0, 2.0, 0.0), radius_m=2.0, speed_mps=1.0, phase_rad=math.pi / 2, clockwise=True)
    p = pose_at(cw, math.pi)
    np.testing.assert_allclose(p.position_m, [3.0, 2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(p.velocity_mps, [0.0, -1.0, 0.0], atol=1e-12)
    assert p.yaw_rad == pytest.approx(-math.pi / 2)
    assert cw.cycle_s == pytest.approx(4 * math.pi)
    np.testing.assert_allclose(pose_at(cw, 1.0 + cw.cycle_s).position_m, pose_at(cw, 1.0).position_m, atol=1e-9)


def test_circle_before_start_stands_still():
    m = CircleMotion((0, 0, 0), 3.0, 1.2, phase_rad=0.0, start_s=5.0)
    p = pose_at(m, 2.0)
    np.testing.assert_allclose(p.position_m, [3.0, 0.0, 0.0])
    assert not p.moving and np.all(p.velocity_mps == 0)


def test_vectorised_equals_scalar():
    rng = np.random.default_rng(0)
    t = rng.uniform(-2.0, 40.0, 50)
    for m in (_square_path(), _square_path(loop=False), CircleMotion((0, 0, 0), 2.0, 1.3, 0.4, True)):
        P, yaw, V, mov = poses_at(m, t)
        np.testing.assert_allclose(positions_at(m, t), P)
        for i in range(len(t)):
            p = pose_at(m, t[i])
            np.testing.assert_allclose(P[i], p.position_m)
            assert yaw[i] == pytest.approx(p.yaw_rad)
            np.testing.assert_allclose(V[i], p.velocity_mps)
            assert mov[i] == p.moving


def test_pose_transform_places_actor_frame():
    p = pose_at(_square_path(), 5.5)  # at (4, 1, 0) heading north
    T = p.T_world_actor
    np.testing.assert_allclose(T @ [1.0, 0.0, 0.0, 1.0], [4.0, 2.0, 0.0, 1.0], atol=1e-12)  # x forward = north


def test_validation():
    with pytest.raises(MotionFormatError, match="at least 2 waypoints"):
        PathMotion((Waypoint((0, 0, 0), 1.0),))
    with pytest.raises(MotionFormatError, match="speed_mps"):
        Waypoint((0, 0, 0), 0.0)
    with pytest.raises(MotionFormatError, match="pause_s"):
        Waypoint((0, 0, 0), 1.0, -1.0)
    with pytest.raises(MotionFormatError, match="do not repeat the first waypoint"):
        PathMotion((Waypoint((0, 0, 0), 1.0), Waypoint((3, 0, 0), 1.0), Waypoint((0, 0, 0), 1.0)))
    with pytest.raises(MotionFormatError, match="radius_m"):
        CircleMotion((0, 0, 0), 0.0, 1.0)
    with pytest.raises(MotionFormatError, match="position_m"):
        Waypoint((0, 0), 1.0)


def test_parse_path_and_circle():
    m = parse_motion(
        {
            "type": "path",
            "loop": False,
            "start_s": 2.0,
            "waypoints": [{"position_m": [0, 0, 0], "speed_mps": 1.2}, {"position_m": [6, 0, 0], "speed_mps": 1.0, "pause_s": 3}],
        }
    )
    assert isinstance(m, PathMotion) and not m.loop and m.start_s == 2.0
    assert m.waypoints[1] == Waypoint((6.0, 0.0, 0.0), 1.0, 3.0)
    c = parse_motion({"type": "circle", "center_m": [1, 2, 0], "radius_m": 5, "speed_mps": 1.1, "phase_deg": 90, "clockwise": True})
    assert isinstance(c, CircleMotion) and c.clockwise
    assert c.phase_rad == pytest.approx(math.pi / 2)


@pytest.mark.parametrize(
    "table, match",
    [
        ({"type": "walk"}, r"motion\.type: unknown motion type 'walk'"),
        ({"waypoints": []}, r"motion\.type: missing required field"),
        ({"type": "path", "waypoints": [{"position_m": [0, 0, 0], "speed_mps": 1}]}, r"motion\.waypoints: a path needs at least 2"),
        ({"type": "path", "waypoints": [{"position_m": [0, 0, 0], "speed_mps": 1}, {"position_m": [1, 0, 0], "speed_mps": -1}]}, r"waypoints\[1\]\.speed_mps: must be > 0"),
        ({"type": "path", "waypoints": [{"position_m": [0, 0, 0], "speed_mps": "1"}, {"position_m": [1, 0, 0], "speed_mps": 1}]}, r"waypoints\[0\]\.speed_mps: expected a finite number"),
        ({"type": "path", "waypoints": [{"position_m": [0, 0], "speed_mps": 1}, {"position_m": [1, 0, 0], "speed_mps": 1}]}, r"waypoints\[0\]\.position_m"),
        ({"type": "path", "waypoints": [{"position_m": [0, 0, 0], "speed": 1}]}, r"waypoints\[0\]\.speed: unknown field"),
        ({"type": "path", "loop": "yes", "waypoints": [{"position_m": [0, 0, 0], "speed_mps": 1}, {"position_m": [1, 0, 0], "speed_mps": 1}]}, r"motion\.loop: expected true or false"),
        ({"type": "circle", "center_m": [0, 0, 0], "radius_m": -2, "speed_mps": 1}, r"motion\.radius_m: must be > 0"),
        ({"type": "circle", "center_m": [0, 0, 0], "radius_m": 2}, r"motion\.speed_mps: missing required field"),
        ({"type": "circle", "center_m": [0, 0, 0], "radius_m": 2, "speed_mps": 1, "phase_rad": 1}, r"motion\.phase_rad: unknown field"),
        ([1, 2], r"motion: expected a table"),
    ],
)
def test_parse_errors_name_the_field(table, match):
    with pytest.raises(MotionFormatError, match=match):
        parse_motion(table)


def test_parse_error_prefix():
    with pytest.raises(MotionFormatError, match=r"^f\.toml: person: motion\.radius_m"):
        parse_motion({"type": "circle", "center_m": [0, 0, 0], "radius_m": 0, "speed_mps": 1}, where="f.toml: person: motion")
