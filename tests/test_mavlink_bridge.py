"""MavlinkBridge against a scripted vehicle on the in-memory link: heartbeat, setpoint
encoding and clipping, trajectory sampling, steady streaming under load, command ACKs."""

import threading
import time

import numpy as np
import pytest

from onfly.mavlink import frames
from onfly.mavlink.bridge import (
    TYPE_MASK,
    BridgeConfig,
    BridgeError,
    CommandRejectedError,
    CommandTimeoutError,
    MavlinkBridge,
    SafetyLimits,
    Setpoint,
    SetpointKind,
)
from onfly.mavlink.link import memory_link_pair, mavlink2
from planning.trajectory import Trajectory

M = mavlink2


class ScriptedVehicle:
    """Vehicle end of a memory link: telemetry at 50 Hz, heartbeat at 5 Hz, scripted ACKs.

    ``results[cmd]`` is the MAV_RESULT to answer (default ACCEPTED); None means never answer.
    Every received message is kept in ``received`` as ``(t_monotonic, msg)``.
    """

    def __init__(self, link, p_enu=(0.0, 0.0, 1.0), yaw_enu=0.0):
        self.link = link
        self.p_enu = np.array(p_enu, dtype=float)
        self.yaw_enu = yaw_enu
        self.results = {}
        self.received = []
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self):
        self.link.connect()
        self.thread.start()
        return self

    def stop(self):
        self._stop.set()
        self.thread.join(2)

    def of_type(self, mtype):
        return [(t, m) for t, m in list(self.received) if m.get_type() == mtype]

    def _run(self):
        next_tel = next_hb = time.monotonic()
        while not self._stop.is_set():
            msg = self.link.recv(0.005)
            now = time.monotonic()
            if msg is not None:
                self.received.append((now, msg))
                if msg.get_type() == "COMMAND_LONG":
                    res = self.results.get(msg.command, M.MAV_RESULT_ACCEPTED)
                    if res is not None:
                        self.link.send(self.link.mav.command_ack_encode(msg.command, res, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
            tb = int((now - self._t0) * 1000)
            if now >= next_tel:
                ned = frames.ned_from_enu(self.p_enu)
                self.link.send(self.link.mav.local_position_ned_encode(tb, *ned, 0.0, 0.0, 0.0))
                self.link.send(self.link.mav.attitude_encode(tb, 0.0, 0.0, frames.yaw_ned_from_enu(self.yaw_enu), 0.0, 0.0, 0.0))
                next_tel += 0.02
            if now >= next_hb:
                self.link.send(self.link.mav.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, 1, 0, M.MAV_STATE_STANDBY))
                next_hb += 0.2


@pytest.fixture
def rig():
    a, b = memory_link_pair(1, 191, 1, 1)
    vehicle = ScriptedVehicle(b).start()
    cfg = BridgeConfig(heartbeat_period_s=0.1, command_timeout_s=0.15, command_retries=2,
                       limits=SafetyLimits(v_max_mps=2.0, a_max_mps2=1.0, leash_m=3.0, fence_min_m=(-10, -10, 0), fence_max_m=(10, 10, 5)))
    bridge = MavlinkBridge(a, cfg).start()
    bridge.wait_for_vehicle(2.0)
    bridge.wait_for_state(2.0)
    yield bridge, vehicle
    bridge.stop()
    vehicle.stop()


def test_companion_heartbeat_identity_and_rate(rig):
    bridge, vehicle = rig
    time.sleep(0.55)
    hbs = vehicle.of_type("HEARTBEAT")
    assert 4 <= len(hbs) <= 8  # 0.1 s period over ~0.6 s
    m = hbs[-1][1]
    assert m.type == M.MAV_TYPE_ONBOARD_CONTROLLER and m.autopilot == M.MAV_AUTOPILOT_INVALID
    assert (m.get_srcSystem(), m.get_srcComponent()) == (1, M.MAV_COMP_ID_ONBOARD_COMPUTER)
    assert vehicle.of_type("SET_POSITION_TARGET_LOCAL_NED") == []  # nothing before start_streaming


def test_type_masks_are_the_documented_values():
    assert TYPE_MASK[SetpointKind.TRACK] == 0x0800
    assert TYPE_MASK[SetpointKind.HOLD] == 0x09F8
    assert TYPE_MASK[SetpointKind.BRAKE] == 0x09C7


def test_send_setpoint_clips_and_encodes_ned(rig):
    bridge, vehicle = rig
    sp = Setpoint(0.0, SetpointKind.TRACK, p=[20.0, 0.0, 1.0], v=[3.0, 4.0, 0.0], a=[0.0, 0.0, 0.5], yaw=np.pi / 2)
    sent = bridge.send_setpoint(sp)
    assert sent.clipped
    np.testing.assert_allclose(sent.p, [3.0, 0.0, 1.0])  # 3 m leash around the vehicle at (0, 0, 1)
    np.testing.assert_allclose(sent.v, [1.2, 1.6, 0.0])  # norm 5 -> 2
    np.testing.assert_allclose(sent.a, [0.0, 0.0, 0.5])  # within limits, untouched
    unclipped = bridge.send_setpoint(Setpoint(0.0, SetpointKind.TRACK, [1.0, 0.0, 1.0], [0.1, 0, 0], [0, 0, 0], 0.0))
    assert not unclipped.clipped
    time.sleep(0.1)
    msgs = [m for _, m in vehicle.of_type("SET_POSITION_TARGET_LOCAL_NED")]
    m = msgs[0]
    assert m.coordinate_frame == M.MAV_FRAME_LOCAL_NED and m.type_mask == 0x0800
    assert (m.target_system, m.target_component) == (1, 1)
    np.testing.assert_allclose([m.x, m.y, m.z], [0.0, 3.0, -1.0], atol=1e-6)
    np.testing.assert_allclose([m.vx, m.vy, m.vz], [1.6, 1.2, 0.0], atol=1e-6)
    np.testing.assert_allclose([m.afx, m.afy, m.afz], [0.0, 0.0, -0.5], atol=1e-6)
    assert m.yaw == pytest.approx(0.0, abs=1e-6)  # ENU pi/2 (north) is NED 0


def test_fence_clips_position_and_bad_setpoints_are_refused():
    with pytest.raises(ValueError, match="not finite"):
        Setpoint(0.0, SetpointKind.TRACK, [np.nan, 0, 0], [0, 0, 0], [0, 0, 0], 0.0)
    with pytest.raises(ValueError, match="shape"):
        Setpoint(0.0, SetpointKind.TRACK, [0, 0], [0, 0, 0], [0, 0, 0], 0.0)
    a, _ = memory_link_pair(1, 191, 1, 1)
    bridge = MavlinkBridge(a, BridgeConfig(limits=SafetyLimits(leash_m=100.0, fence_min_m=(-1, -1, 0), fence_max_m=(1, 1, 2))))
    out = bridge.clip_setpoint(Setpoint(0.0, SetpointKind.HOLD, [5.0, -5.0, -1.0], [0, 0, 0], [0, 0, 0], 0.0), None)
    np.testing.assert_allclose(out.p, [1.0, -1.0, 0.0])


def test_vehicle_limits_are_the_planners_and_the_volume_is_the_fence():
    from planning.planner_config import PlannerConfig
    from planning.volume import FlightVolume

    pc = PlannerConfig()
    vol = FlightVolume(np.array([-2.0, -3.0, 0.0]), np.array([4.0, 5.0, 3.0]))
    lim = SafetyLimits.for_vehicle(pc.v_max_mps, pc.a_max_mps2, vol, leash_m=100.0)
    assert lim.v_max_mps == pytest.approx(1.01 * pc.v_max_mps) and lim.a_max_mps2 == pytest.approx(1.01 * pc.a_max_mps2)
    assert lim.fence_min_m == (-2.0, -3.0, 0.0) and lim.fence_max_m == (4.0, 5.0, 3.0)
    a, _ = memory_link_pair(1, 191, 1, 1)
    bridge = MavlinkBridge(a, BridgeConfig(limits=lim))
    # |a| = 1.04 m/s^2 (the per-axis planner's worst case) leaves at the norm limit
    out = bridge.clip_setpoint(Setpoint(0.0, SetpointKind.TRACK, [9.0, 0.0, 1.0], [0.6, 0.6, 0.0], [0.6, 0.6, 0.6], 0.0), None)
    assert np.linalg.norm(out.a) == pytest.approx(lim.a_max_mps2) and np.linalg.norm(out.v) == pytest.approx(lim.v_max_mps)
    np.testing.assert_allclose(out.p, [4.0, 0.0, 1.0])


def test_streamer_samples_the_trajectory_at_a_steady_rate_while_the_main_thread_is_busy(rig):
    bridge, vehicle = rig
    t0 = bridge.clock()
    n, dt = 50, 0.1
    p = np.zeros((n + 1, 3))
    p[:, 0] = np.linspace(0, 1.0, n + 1)
    p[:, 2] = 1.0
    v = np.zeros((n + 1, 3))
    v[:, 0] = 0.2
    traj = Trajectory(t0, dt, p, v, np.linspace(0, 0.5, n + 1), np.zeros((n, 3)), np.full(n, 0.1))
    bridge.set_trajectory(traj)
    bridge.start_streaming()
    # A planner hogging the interpreter (pure Python, holds the GIL between switches) for 1 s
    t_busy = time.monotonic()
    x = 0
    while time.monotonic() - t_busy < 1.0:
        x += 1
    time.sleep(0.2)
    bridge.stop_streaming()
    times = np.array([t for t, _ in vehicle.of_type("SET_POSITION_TARGET_LOCAL_NED")])
    rate = (len(times) - 1) / (times[-1] - times[0])
    assert 16.0 <= rate <= 24.0
    assert np.max(np.diff(times)) < 0.2
    # What was sent equals the trajectory sampled at the send time (all TRACK, in ENU)
    sent = list(bridge.sent)
    assert all(s.kind is SetpointKind.TRACK for s in sent)
    for s in sent[::5]:
        p_ref, v_ref, a_ref, yaw_ref, _ = traj.sample(s.t_s)
        np.testing.assert_allclose(s.p, p_ref, atol=1e-9)
        np.testing.assert_allclose(s.v, v_ref, atol=1e-9)
        assert s.yaw == pytest.approx(yaw_ref)


def test_without_a_plan_the_streamer_holds_at_a_fixed_point(rig):
    bridge, vehicle = rig
    bridge.start_streaming()
    time.sleep(0.3)
    vehicle.p_enu = np.array([0.5, 0.5, 1.0])  # drift: the hold point must not follow it
    time.sleep(0.3)
    sent = list(bridge.sent)
    assert len(sent) >= 8 and all(s.kind is SetpointKind.HOLD for s in sent)
    np.testing.assert_allclose(np.array([s.p for s in sent]), np.tile([0.0, 0.0, 1.0], (len(sent), 1)), atol=1e-6)


def test_setpoint_source_callback_and_its_failure(rig):
    bridge, vehicle = rig
    calls = []

    def source(t):
        calls.append(t)
        if len(calls) > 5:
            raise RuntimeError("planner bug")
        return Setpoint(t, SetpointKind.TRACK, [0.2, 0, 1], [0, 0, 0], [0, 0, 0], 0.0)

    bridge.set_setpoint_source(source)
    bridge.start_streaming()
    time.sleep(0.5)
    kinds = [s.kind for s in bridge.sent]
    assert kinds[:5] == [SetpointKind.TRACK] * 5
    assert set(kinds[6:]) == {SetpointKind.HOLD}  # a raising source holds, the streamer survives
    assert bridge.running


def test_commands_ack_reject_and_timeout_with_retries(rig):
    bridge, vehicle = rig
    assert bridge.command_long(M.MAV_CMD_COMPONENT_ARM_DISARM, (1,)) == M.MAV_RESULT_ACCEPTED
    vehicle.results[M.MAV_CMD_DO_SET_MODE] = M.MAV_RESULT_DENIED
    with pytest.raises(CommandRejectedError, match="MAV_CMD_DO_SET_MODE rejected by the vehicle: MAV_RESULT_DENIED"):
        bridge.command(M.MAV_CMD_DO_SET_MODE, (1, 6))
    vehicle.results[M.MAV_CMD_NAV_LAND] = None
    t0 = time.monotonic()
    with pytest.raises(CommandTimeoutError, match="no COMMAND_ACK for MAV_CMD_NAV_LAND after 3 attempt"):
        bridge.command(M.MAV_CMD_NAV_LAND)
    assert 0.4 <= time.monotonic() - t0 < 1.5
    confirmations = [m.confirmation for _, m in vehicle.of_type("COMMAND_LONG") if m.command == M.MAV_CMD_NAV_LAND]
    assert confirmations == [0, 1, 2]


def test_message_interval_requests(rig):
    bridge, vehicle = rig
    vehicle.results[M.MAV_CMD_SET_MESSAGE_INTERVAL] = M.MAV_RESULT_ACCEPTED
    res = bridge.request_message_intervals()
    assert res == {M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0, M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 0}
    reqs = [m for _, m in vehicle.of_type("COMMAND_LONG") if m.command == M.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert sorted(int(m.param1) for m in reqs) == [31, 32]
    assert all(m.param2 == pytest.approx(20000.0) for m in reqs)  # 50 Hz


def test_release_is_final(rig):
    bridge, vehicle = rig
    bridge.start_streaming()
    time.sleep(0.2)
    bridge.release("test takeover")
    n = len(vehicle.of_type("SET_POSITION_TARGET_LOCAL_NED"))
    time.sleep(0.3)
    assert len(vehicle.of_type("SET_POSITION_TARGET_LOCAL_NED")) <= n + 1
    with pytest.raises(BridgeError, match="released"):
        bridge.start_streaming()
    with pytest.raises(BridgeError, match="released"):
        bridge.send_setpoint(Setpoint.hold(0.0, [0, 0, 1], 0.0))
    assert bridge.release_reason == "test takeover"


def test_trajectory_type_and_config_validation():
    a, _ = memory_link_pair(1, 191, 1, 1)
    bridge = MavlinkBridge(a)
    with pytest.raises(TypeError, match="Trajectory"):
        bridge.set_trajectory(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="setpoint_rate_hz"):
        BridgeConfig(setpoint_rate_hz=1.0)
    with pytest.raises(ValueError, match="leash_m"):
        SafetyLimits(leash_m=0.0)
    with pytest.raises(ValueError, match="fence_min_m must be below"):
        SafetyLimits(fence_min_m=(0, 0, 0), fence_max_m=(1, -1, 1))
    with pytest.raises(BridgeError, match="started bridge"):
        bridge.command_long(M.MAV_CMD_COMPONENT_ARM_DISARM, (1,))
    wrong, _ = memory_link_pair(1, 190, 1, 1)
    with pytest.raises(ValueError, match="link signs as 1/190 but the bridge config says 1/191"):
        MavlinkBridge(wrong)
    from_url = MavlinkBridge.from_url("udpin:127.0.0.1:0", BridgeConfig(source_system=7))
    assert (from_url.link.source_system, from_url.link.source_component) == (7, 191)
    with pytest.raises(ValueError, match="source_system must be in"):
        BridgeConfig(source_system=0)
