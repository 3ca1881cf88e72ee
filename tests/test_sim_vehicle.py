"""SimMavlinkVehicle: PX4 and ArduCopter rules, telemetry rates and clocks, the point-mass
model's limits, the loopback camera channel, and the `onfly sim-vehicle` command."""

import argparse
import math
import socket
import struct
import threading
import time

import numpy as np
import pytest

from onfly.cli import CliError
from onfly.commands import sim_vehicle as sim_vehicle_cmd
from onfly.mavlink import frames
from onfly.mavlink.autopilot import ARDUCOPTER_MODE, PX4_MAIN, px4_main_mode
from onfly.mavlink.camera_channel import FrameChannelError, FrameClient, FrameServer, decode_observation, encode_observation, parse_tcp_url
from onfly.mavlink.link import memory_link_pair, mavlink2
from onfly.mavlink.sim_vehicle import PointMassModel, SimMavlinkVehicle, SimVehicleConfig, _Target
from onfly.mavlink.state import StateReader
from onfly.observation import Observation
from planning.camera import PinholeCamera
from planning.frames import body_transform, cam_transform_from_body, wrap_angle
from vlm.types import FrameAnnotation, VisibleObject

M = mavlink2


class Companion:
    """Raw companion end: records every message, answers nothing, sends what the test says."""

    def __init__(self, link):
        self.link = link
        self.received = []
        self._stop = threading.Event()
        link.connect()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        while not self._stop.is_set():
            m = self.link.recv(0.01)
            if m is not None:
                self.received.append((time.monotonic(), m))

    def stop(self):
        self._stop.set()
        self._t.join(1)

    def of_type(self, mtype):
        return [(t, m) for t, m in list(self.received) if m.get_type() == mtype]

    def command(self, cmd, *params, timeout_s=1.0):
        n0 = len(self.of_type("COMMAND_ACK"))
        p = list(params) + [0.0] * (7 - len(params))
        self.link.send(self.link.mav.command_long_encode(1, 1, cmd, 0, *p))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            acks = self.of_type("COMMAND_ACK")[n0:]
            for _, a in acks:
                if a.command == cmd:
                    return a.result
            time.sleep(0.005)
        raise AssertionError(f"no ACK for {cmd}")

    def setpoint(self, p_enu, yaw_enu=0.0, mask=0x09F8, target_system=1):
        ned = frames.ned_from_enu(np.asarray(p_enu, float))
        self.link.send(self.link.mav.set_position_target_local_ned_encode(
            0, target_system, 1, M.MAV_FRAME_LOCAL_NED, mask, *ned, 0, 0, 0, 0, 0, 0, frames.yaw_ned_from_enu(yaw_enu), 0))

    def stream(self, p_enu, duration_s, rate_hz=20.0):
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            self.setpoint(p_enu)
            time.sleep(1.0 / rate_hz)


def rig(**kw):
    a, b = memory_link_pair(1, 191, 1, 1)
    # Stiff gains: these tests are about the rules, not the dynamics (kept short in wall time).
    cfg = dict(heartbeat_period_s=0.2, offboard_loss_timeout_s=0.3, guided_timeout_s=0.5,
               k_pos=4.0, k_vel=8.0, a_max_mps2=8.0)
    cfg.update(kw)
    vehicle = SimMavlinkVehicle(b, SimVehicleConfig(**cfg)).start()
    return Companion(a), vehicle


@pytest.fixture
def px4():
    c, v = rig(autopilot="px4")
    yield c, v
    c.stop()
    v.stop()


@pytest.fixture
def ardu():
    c, v = rig(autopilot="ardupilot")
    yield c, v
    c.stop()
    v.stop()


def test_point_mass_tracks_within_limits():
    cfg = SimVehicleConfig(v_max_mps=2.0, a_max_mps2=3.0, yaw_rate_max_radps=0.5)
    model = PointMassModel(cfg)
    target = _Target(p=np.array([10.0, -5.0, 3.0]), yaw=2.0)
    speeds, accs, rates = [], [], []
    for _ in range(3000):
        model.step(0.01, target, armed=True)
        speeds.append(np.linalg.norm(model.v))
        accs.append(np.linalg.norm(model.a))
        rates.append(abs(model.yaw_rate))
    np.testing.assert_allclose(model.p, target.p, atol=0.01)
    assert model.yaw == pytest.approx(2.0, abs=1e-3)
    assert max(speeds) <= 2.0 + 1e-9 and max(accs) <= 3.0 + 1e-9 and max(rates) <= 0.5 + 1e-9
    R = model.R_enu_flu()
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    # Disarmed on the ground: nothing moves whatever the target
    grounded = PointMassModel(cfg)
    for _ in range(100):
        grounded.step(0.01, target, armed=False)
    np.testing.assert_array_equal(grounded.p, [0.0, 0.0, 0.0])


def test_config_validation():
    with pytest.raises(ValueError, match="autopilot must be 'px4' or 'ardupilot'"):
        SimVehicleConfig(autopilot="inav")
    with pytest.raises(ValueError, match="offboard_loss_timeout_s must be positive"):
        SimVehicleConfig(offboard_loss_timeout_s=0)
    with pytest.raises(ValueError, match="initial_position_m"):
        SimVehicleConfig(initial_position_m=(0, 0, -1))


def test_heartbeat_and_telemetry_rates_and_ids(px4):
    c, v = px4
    time.sleep(0.6)
    hbs, pos, att = c.of_type("HEARTBEAT"), c.of_type("LOCAL_POSITION_NED"), c.of_type("ATTITUDE_QUATERNION")
    assert 3 <= len(hbs) <= 5  # 0.2 s period
    assert 20 <= len(pos) <= 34 and 20 <= len(att) <= 34  # 50 Hz
    hb = hbs[-1][1]
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert px4_main_mode(hb.custom_mode) == PX4_MAIN["auto"] and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    tb = np.array([m.time_boot_ms for _, m in pos])
    assert np.all(np.diff(tb) > 0)
    # SET_MESSAGE_INTERVAL: position at 10 Hz
    assert c.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100000) == M.MAV_RESULT_ACCEPTED
    n0 = len(c.of_type("LOCAL_POSITION_NED"))
    time.sleep(0.6)
    assert 4 <= len(c.of_type("LOCAL_POSITION_NED")) - n0 <= 8
    assert c.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 100000) == M.MAV_RESULT_DENIED
    assert c.command(M.MAV_CMD_DO_MOTOR_TEST) == M.MAV_RESULT_UNSUPPORTED


def test_px4_offboard_rules(px4):
    c, v = px4
    assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert c.command(M.MAV_CMD_DO_SET_MODE, 1, 6) == M.MAV_RESULT_TEMPORARILY_REJECTED  # no setpoint yet
    c.setpoint([0, 0, 1.0])  # one recent setpoint is enough (COM_OF_LOSS_T), no pre-stream duration
    time.sleep(0.02)
    assert c.command(M.MAV_CMD_DO_SET_MODE, 1, 6) == M.MAV_RESULT_ACCEPTED
    c.stream([0, 0, 1.0], 1.0)
    assert v.mode_name == "offboard" and v.position_enu()[2] == pytest.approx(1.0, abs=0.1)
    # in the air: disarm refused unless forced
    assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0) == M.MAV_RESULT_DENIED
    # stream stops -> COM_OBL_RC_ACT after COM_OF_LOSS_T: the indoor setting's Hold (AUTO.LOITER)
    assert v.setpoint_times
    time.sleep(0.6)
    t_lost = v.first_event("mode auto.loiter: offboard lost")
    assert t_lost is not None and 0.3 <= t_lost - v.setpoint_times[-1] <= 0.3 + 0.1  # COM_OF_LOSS_T after the last setpoint
    assert v.position_enu()[2] == pytest.approx(1.0, abs=0.15)
    last_hb = c.of_type("HEARTBEAT")[-1][1]
    assert px4_main_mode(last_hb.custom_mode) == PX4_MAIN["auto"] and last_hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    # setpoints for another system are not followed
    c.stream([5.0, 0, 1.0], 0.2)
    n = v.foreign_setpoints
    for _ in range(5):
        c.setpoint([9.0, 9.0, 9.0], target_system=7)
    time.sleep(0.05)
    assert v.foreign_setpoints == n + 5
    # an AMSL take-off altitude needs a global origin the indoor vehicle does not have
    assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == M.MAV_RESULT_DENIED


def test_ardupilot_guided_rules(ardu):
    c, v = ardu
    assert c.command(M.MAV_CMD_DO_SET_MODE, 1, ARDUCOPTER_MODE["guided"]) == M.MAV_RESULT_ACCEPTED
    assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == M.MAV_RESULT_FAILED  # disarmed
    assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    c.stream([3.0, 0, 2.0], 0.1)  # ignored before takeoff
    assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0) == M.MAV_RESULT_ACCEPTED
    time.sleep(0.9)
    assert v.first_event("takeoff complete") is not None
    np.testing.assert_allclose(v.position_enu(), [0.0, 0.0, 1.0], atol=0.15)
    # a position-only target has no GUID_TIMEOUT: it is held after the stream stops
    c.stream([1.0, 0, 1.0], 0.3)
    time.sleep(1.2)
    assert v.first_event("guided timeout") is None
    assert v.position_enu()[0] == pytest.approx(1.0, abs=0.1)
    # a velocity target times out (0.5 s here, GUID_TIMEOUT = 3 s on ArduCopter): the vehicle stops, stays GUIDED
    vel_mask = 0x09C7
    for _ in range(6):
        c.link.send(c.link.mav.set_position_target_local_ned_encode(
            0, 1, 1, M.MAV_FRAME_LOCAL_NED, vel_mask, 0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0))  # 0.5 m/s north
        time.sleep(0.05)
    assert v.setpoint_times
    time.sleep(0.8)
    t_to = v.first_event("guided timeout")
    assert t_to is not None and 0.5 <= t_to - v.setpoint_times[-1] <= 0.5 + 0.1  # GUID_TIMEOUT after the last target
    assert np.linalg.norm(v.velocity_enu()) < 0.05 and v.position_enu()[1] > 0.1
    assert v.mode_name == "guided"
    assert len(c.of_type("ATTITUDE")) > 50  # ArduPilot reports Euler ATTITUDE
    assert c.of_type("HEARTBEAT")[-1][1].autopilot == M.MAV_AUTOPILOT_ARDUPILOTMEGA


def test_time_boot_wraps_and_the_reader_stays_monotonic():
    a, b = memory_link_pair(1, 191, 1, 1)
    v = SimMavlinkVehicle(b, SimVehicleConfig(boot_time_ms=2**32 - 300)).start()
    a.connect()
    reader = StateReader()
    raw, times = [], []
    end = time.monotonic() + 0.8
    while time.monotonic() < end:
        m = a.recv(0.05)
        if m is None:
            continue
        if reader.handle(m) and m.get_type() == "LOCAL_POSITION_NED" and reader.state() is not None:
            raw.append(m.time_boot_ms)
            times.append(reader.state().t_s)
    v.stop()
    raw = np.array(raw)
    assert raw.max() > 2**32 - 300 and raw.min() < 400  # it did wrap
    t_pos = np.array(times)
    assert np.all(np.diff(t_pos) > 0)


# -- camera channel ----------------------------------------------------------------------------
def make_observation(i, rng):
    cam = PinholeCamera.from_fov(32, 24, 90, 60)
    ids = rng.integers(0, 3, size=(24, 32))
    depth = rng.uniform(0.5, 7.0, size=(24, 32)).astype(np.float32)
    ann = FrameAnnotation(ids, depth, {1: VisibleObject(1, "red van", "van", ("vehicle",)), 2: VisibleObject(2, "gate", "gate", target=False)}, ids * 10)
    T = cam_transform_from_body(body_transform([i, 2.0, 1.0], 0.3 * i))
    return Observation(float(i), rng.integers(0, 255, size=(24, 32, 3), dtype=np.uint8), depth, T, cam, f"f{i}", annotation=ann)


def test_frame_channel_round_trip_over_tcp():
    rng = np.random.default_rng(0)
    frames_out = [make_observation(i, rng) for i in range(5)]
    it = iter(frames_out)
    with FrameServer(lambda: next(it, None), rate_hz=50.0) as server:
        with FrameClient(server.url, timeout_s=2.0) as client:
            got = [client.read() for _ in range(5)]
    for a, b in zip(frames_out, got):
        assert b.frame_id == a.frame_id and b.t_s == a.t_s
        np.testing.assert_array_equal(b.rgb, a.rgb)
        np.testing.assert_array_equal(b.depth_m, a.depth_m)
        np.testing.assert_allclose(b.T_world_cam, a.T_world_cam)
        assert b.camera == a.camera
        np.testing.assert_array_equal(b.annotation.instance_ids, a.annotation.instance_ids)
        np.testing.assert_array_equal(b.annotation.semantic_ids, a.annotation.semantic_ids)
        assert b.annotation.objects[1].name == "red van" and b.annotation.objects[1].aliases == ("vehicle",)


def test_frame_channel_rejects_bad_input():
    rng = np.random.default_rng(1)
    payload = encode_observation(make_observation(0, rng))[8:]
    with pytest.raises(FrameChannelError, match="not a valid npz"):
        decode_observation(b"garbage" * 10)
    with pytest.raises(FrameChannelError, match="tcp://127.0.0.1:PORT"):
        parse_tcp_url("udp://127.0.0.1:5")
    with pytest.raises(FrameChannelError, match="loopback only"):
        FrameServer(lambda: None, host="0.0.0.0")
    with FrameServer(lambda: make_observation(0, rng), rate_hz=20.0) as server:
        with FrameClient(server.url, max_frame_bytes=1000) as client:
            with pytest.raises(FrameChannelError, match="exceeds max_frame_bytes=1000"):
                client.read()
    assert len(payload) > 1000


# -- CLI -------------------------------------------------------------------------------------------
def _cli(argv):
    """Parse ``argv`` with the command's own arguments (no other CLI modules imported)."""
    parser = argparse.ArgumentParser(prog="onfly sim-vehicle")
    sim_vehicle_cmd.add_arguments(parser)
    return sim_vehicle_cmd.run(parser.parse_args(argv))


def test_sim_vehicle_in_process_hands_its_status_lines_to_the_callers_writer(capsys):
    parser = argparse.ArgumentParser(prog="onfly sim-vehicle")
    sim_vehicle_cmd.add_arguments(parser)
    lines = []
    args = parser.parse_args(["--mavlink", "udpout:127.0.0.1:9", "--autopilot", "px4", "--duration-s", "0.3"])
    assert sim_vehicle_cmd.run(args, emit=lines.append) == 0
    assert capsys.readouterr().out == ""  # nothing printed behind the caller's back
    assert lines[0].startswith("onfly sim-vehicle: px4 vehicle (indoor, system 1) on udpout:127.0.0.1:9")
    assert any("armed=False" in line for line in lines[1:])  # the first state line: disarmed on the ground


def test_cli_sim_vehicle_serves_heartbeats(capsys):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    rc = _cli(["--mavlink", f"udpout:127.0.0.1:{port}", "--autopilot", "ardupilot", "--duration-s", "0.4"])
    assert rc == 0
    parser = M.MAVLink(None)
    parser.robust_parsing = True
    heartbeats = []
    sock.setblocking(False)
    while True:
        try:
            data = sock.recv(4096)
        except BlockingIOError:
            break
        for m in parser.parse_buffer(data) or []:
            if m.get_type() == "HEARTBEAT":
                heartbeats.append(m)
    sock.close()
    assert heartbeats and heartbeats[0].autopilot == M.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert "ardupilot vehicle (indoor, system 1)" in capsys.readouterr().out
    with pytest.raises(CliError, match="unsupported link URL 'bogus:1'"):
        _cli(["--mavlink", "bogus:1"])
    with pytest.raises(CliError, match="--duration-s must be positive"):
        _cli(["--duration-s", "-1"])
    assert sim_vehicle_cmd.NAME == "sim-vehicle"


@pytest.mark.slow
def test_two_processes_cli_vehicle_and_bridge_fly_px4_offboard():
    """`onfly sim-vehicle` in its own process, the bridge here: engage OFFBOARD and climb."""
    import subprocess
    import sys

    from onfly.mavlink.autopilot import OffboardConfig, Px4Offboard
    from onfly.mavlink.bridge import MavlinkBridge
    from planning.trajectory import Trajectory

    bridge = MavlinkBridge.from_url("udpin:127.0.0.1:0")
    bridge.link.connect()
    port = bridge.link.local_address[1]
    proc = subprocess.Popen(
        [sys.executable, "-c", "import sys; from onfly.cli import main; sys.exit(main(sys.argv[1:]))",
         "sim-vehicle", "--mavlink", f"udpout:127.0.0.1:{port}", "--duration-s", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    try:
        bridge.start()
        bridge.wait_for_vehicle(15.0)
        Px4Offboard(bridge, OffboardConfig(prestream_s=1.2)).engage()
        n, dt = 20, 0.1
        p = np.zeros((n + 1, 3))
        p[:, 2] = np.linspace(0, 1.0, n + 1)
        v = np.zeros((n + 1, 3))
        v[:, 2] = 0.5
        bridge.set_trajectory(Trajectory(bridge.clock(), dt, p, v, np.zeros(n + 1), np.zeros((n, 3)), np.zeros(n)))
        time.sleep(4.0)
        assert bridge.state().p[2] == pytest.approx(1.0, abs=0.1)
        assert bridge.status().custom_mode == 6 << 16 and bridge.status().armed
    finally:
        bridge.stop()
        proc.terminate()
        proc.wait(5)


# -- the stricter rules, one by one (PX4 / ArduCopter behaviour cited in onfly/mavlink/sim_vehicle.py) --
def _wait(pred, timeout_s=3.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return False


def _px4_take_off(c, v, timeout_s=4.0):
    """PX4 NAV_TAKEOFF (MIS_TAKEOFF_ALT), arm, and wait for AUTO.LOITER at the top."""
    nan = float("nan")
    assert c.command(M.MAV_CMD_NAV_TAKEOFF, nan, nan, nan, nan, nan, nan, nan) == M.MAV_RESULT_ACCEPTED
    assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert _wait(lambda: v.mode_name == "auto.loiter", timeout_s)


def test_commands_with_nan_params_request_message_and_parameters():
    c, v = rig(autopilot="px4", params=(("COM_DISARM_PRFLT", 30.0),))
    try:
        nan = float("nan")
        # MAVSDK's arm: NaN in every unused parameter must not break the handler
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, nan, nan, nan, nan, nan, nan) == M.MAV_RESULT_ACCEPTED and v.armed
        assert c.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, nan) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: c.of_type("AUTOPILOT_VERSION"))
        av = c.of_type("AUTOPILOT_VERSION")[-1][1]
        assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT and av.capabilities & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        assert c.command(M.MAV_CMD_GET_HOME_POSITION) == M.MAV_RESULT_ACCEPTED  # home was set at arming
        assert _wait(lambda: c.of_type("HOME_POSITION"))
        # PX4 sends integer parameters bytewise in the float field
        c.link.send(c.link.mav.param_request_read_encode(1, 1, b"COM_OBL_RC_ACT", -1))
        assert _wait(lambda: c.of_type("PARAM_VALUE"))
        pv = c.of_type("PARAM_VALUE")[-1][1]
        assert pv.param_type == M.MAV_PARAM_TYPE_INT32 and struct.unpack("<i", struct.pack("<f", pv.param_value))[0] == 5  # indoor: Hold
    finally:
        c.stop()
        v.stop()


def test_px4_per_axis_type_mask_preflight_disarm_and_land_detector_in_any_mode():
    c, v = rig(autopilot="px4", params=(("COM_DISARM_PRFLT", 0.6), ("LNDMC_TRIG_TIME", 0.2), ("COM_DISARM_LAND", 0.3)))
    try:
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: not v.armed, 2.0)  # no take-off within COM_DISARM_PRFLT
        # on the vehicle's own clock: the client's time after the ACK is later than the arming
        # by the ACK's trip (a loaded machine measured 0.597 s from it)
        assert 0.6 <= v.first_event("disarmed: no take-off") - v.first_event("armed") <= 0.9
        # x/y position with z velocity (PX4 takes each axis on its own)
        mask = 0x0DE0 | M.POSITION_TARGET_TYPEMASK_Z_IGNORE  # ignore accelerations, yaw rate, z position
        mask &= ~(M.POSITION_TARGET_TYPEMASK_VZ_IGNORE)
        mask |= M.POSITION_TARGET_TYPEMASK_VX_IGNORE | M.POSITION_TARGET_TYPEMASK_VY_IGNORE

        def send(vz_up):
            c.link.send(c.link.mav.set_position_target_local_ned_encode(
                0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask, 1.0, 0.5, 0.0, 0, 0, -vz_up, 0, 0, 0, 0, 0))  # north 1, east 0.5

        send(1.0)
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, 6) == M.MAV_RESULT_ACCEPTED
        end = time.monotonic() + 1.2
        while time.monotonic() < end:
            send(1.0)
            time.sleep(0.05)
        p = v.position_enu()
        assert p[0] == pytest.approx(0.5, abs=0.1) and p[1] == pytest.approx(1.0, abs=0.1) and p[2] > 0.8
        # descend onto the ground still in OFFBOARD: the land detector disarms in any mode
        end = time.monotonic() + 4.0
        while v.armed and time.monotonic() < end:
            send(-1.0)
            time.sleep(0.05)
        assert not v.armed and v.mode_name == "offboard" and v.first_event("landed") is not None
    finally:
        c.stop()
        v.stop()


def test_estimator_frame_is_not_the_scene_frame_and_the_bridge_anchors_its_world():
    from onfly.mavlink.autopilot import OffboardConfig, Px4Offboard
    from onfly.mavlink.bridge import BridgeConfig, MavlinkBridge

    a, b = memory_link_pair(1, 191, 1, 1)
    start, yaw0 = (4.0, -3.0, 0.0), 0.6
    vehicle = SimMavlinkVehicle(b, SimVehicleConfig(heartbeat_period_s=0.2, k_pos=4.0, k_vel=8.0, a_max_mps2=8.0, initial_position_m=start,
                                                    initial_yaw_rad=yaw0, estimator_origin_m=(1.0, 1.0, 0.0), estimator_yaw_rad=-0.9)).start()
    bridge = MavlinkBridge(a, BridgeConfig()).start()
    try:
        bridge.wait_for_vehicle(3.0)
        local = bridge.wait_for_state(3.0)
        # LOCAL_POSITION_NED is relative to the estimator origin, in its rotated frame
        np.testing.assert_allclose(local.p, vehicle.local_from_scene(np.array(start)), atol=0.02)
        assert np.linalg.norm(local.p - np.array(start)) > 1.0
        bridge.anchor_world()
        st = bridge.state()
        np.testing.assert_allclose(st.p, 0.0, atol=0.02)
        assert abs(st.yaw) < 0.02
        Px4Offboard(bridge, OffboardConfig(prestream_s=0.2)).engage()
        from onfly.mavlink.bridge import Setpoint

        bridge.set_setpoint_source(lambda t: Setpoint.hold(t, [1.0, 0.0, 1.5], 0.0))  # 1 m ahead, 1.5 m up, in the world frame
        c0, s0 = np.cos(yaw0), np.sin(yaw0)
        want = np.array([start[0] + c0, start[1] + s0, 1.5])  # ahead = along the start heading in the scene
        assert _wait(lambda: np.linalg.norm(vehicle.position_enu() - want) < 0.05, 6.0), vehicle.position_enu()
        np.testing.assert_allclose(bridge.state().p, [1.0, 0.0, 1.5], atol=0.05)
    finally:
        bridge.stop()
        vehicle.stop()


def test_px4_takeoff_accepted_disarmed_climbs_once_armed_to_mis_takeoff_alt():
    c, v = rig(autopilot="px4", params=(("MIS_TAKEOFF_ALT", 1.0),))
    try:
        nan = float("nan")
        assert c.command(M.MAV_CMD_NAV_TAKEOFF, nan, nan, nan, nan, nan, nan, nan) == M.MAV_RESULT_ACCEPTED
        assert v.mode_name == "auto.takeoff" and not v.armed
        time.sleep(0.3)
        assert v.position_enu()[2] == 0.0  # disarmed: motors off
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: v.mode_name == "auto.loiter", 4.0)  # take-off complete -> Hold
        assert v.position_enu()[2] == pytest.approx(1.0, abs=0.1)
        # a fresh arm in AUTO.LAND is refused: the mode prevents arming
        assert c.command(M.MAV_CMD_NAV_LAND) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: not v.armed, 8.0)
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_FAILED
    finally:
        c.stop()
        v.stop()


# -- Return mode (onfly/mavlink/rtl.py) -------------------------------------------------------
def test_return_altitude_rules_px4_cone_and_arducopter_climb_min_and_cone():
    from onfly.mavlink.rtl import ardu_return_altitude_cm, px4_return_altitude
    from onfly.mavlink.sim_vehicle import ARDUPILOT_PARAMS, PX4_PARAMS

    px4 = {k: v for k, (v, _) in PX4_PARAMS.items()}  # RTL_RETURN_ALT 30, cone 45, RTL_MIN_DIST 10, NAV_ACC_RAD 2
    home = np.zeros(3)
    assert px4_return_altitude([50.0, 0.0, 5.0], home, px4) == 30.0  # far: RTL_RETURN_ALT above home
    assert px4_return_altitude([50.0, 0.0, 40.0], home, px4) == 40.0  # above it: returns at its altitude
    assert px4_return_altitude([1.5, 0.0, 1.0], home, px4) == 3.0  # inside NAV_ACC_RAD: 2 x distance
    assert px4_return_altitude([6.0, 0.0, 1.0], home, px4) == pytest.approx(6.0)  # inside RTL_MIN_DIST: the 45 deg cone
    assert px4_return_altitude([3.0, 0.0, 1.0], home, px4) == pytest.approx(4.0)  # never below 2 x NAV_ACC_RAD outside it
    assert px4_return_altitude([0.0, 0.0, 1.0], home, dict(px4, RTL_CONE_ANG=0)) == 30.0  # no cone
    ardu = {k: v for k, (v, _) in ARDUPILOT_PARAMS.items()}  # RTL_ALT 1500 cm, RTL_CONE_SLOPE 3
    assert ardu_return_altitude_cm([100.0, 0.0, 2.0], home, ardu) == 1500.0
    assert ardu_return_altitude_cm([100.0, 0.0, 2.0], home, dict(ardu, RTL_CLIMB_MIN=2000)) == pytest.approx(2200.0)
    assert ardu_return_altitude_cm([2.0, 0.0, 2.0], home, ardu) == pytest.approx(600.0)  # cone: 2 m x 3
    assert ardu_return_altitude_cm([0.0, 0.0, 2.0], home, ardu) == pytest.approx(200.0)  # never descends
    assert ardu_return_altitude_cm([0.0, 0.0, 0.1], home, ardu) == pytest.approx(30.0)  # RTL_ALT_MIN


def test_return_refused_without_global_position_and_no_gps_indoors():
    c, v = rig(autopilot="px4", params=(("MIS_TAKEOFF_ALT", 1.0),))  # indoor: vision, no global origin
    try:
        _px4_take_off(c, v)
        assert c.command(M.MAV_CMD_NAV_RETURN_TO_LAUNCH) == M.MAV_RESULT_TEMPORARILY_REJECTED
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, PX4_MAIN["auto"], 5) == M.MAV_RESULT_TEMPORARILY_REJECTED  # AUTO.RTL
        assert v.mode_name == "auto.loiter" and v.armed
        assert [t for _, t in v.statustexts].count("Switching to Return is currently not available") == 2
        assert not c.of_type("GPS_RAW_INT") and c.of_type("LOCAL_POSITION_NED")  # no GPS indoors
    finally:
        c.stop()
        v.stop()
    c, v = rig(autopilot="ardupilot")  # indoor ArduCopter: home needs a location, RTL's init fails armed
    try:
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, ARDUCOPTER_MODE["guided"]) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_NAV_RETURN_TO_LAUNCH) == M.MAV_RESULT_FAILED
        assert v.mode_name == "guided" and "Mode change to RTL failed: init failed" in [t for _, t in v.statustexts]
    finally:
        c.stop()
        v.stop()


@pytest.mark.slow  # real time, ~8 s: opt-in (`-m slow`)
def test_px4_offboard_loss_with_return_outdoors_flies_home_and_lands():
    c, v = rig(autopilot="px4", profile="outdoor", params=(("COM_OBL_RC_ACT", 3), ("RTL_RETURN_ALT", 2.5),
                                                           ("LNDMC_TRIG_TIME", 0.3), ("COM_DISARM_LAND", 0.3)))
    try:
        c.setpoint([3.0, 0.0, 1.5])
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, PX4_MAIN["offboard"]) == M.MAV_RESULT_ACCEPTED
        c.stream([3.0, 0.0, 1.5], 2.5)
        np.testing.assert_allclose(v.position_enu(), [3.0, 0.0, 1.5], atol=0.1)
        # the stream stops: COM_OF_LOSS_T later COM_OBL_RC_ACT = 3 (Return), available outdoors
        assert _wait(lambda: v.mode_name == "auto.rtl", 1.0)
        zs = []
        assert _wait(lambda: zs.append(v.position_enu()[2]) or not v.armed, 12.0), v.events
        assert max(zs) == pytest.approx(2.5, abs=0.1)  # 3 m from home: the cone allows 3 m, RTL_RETURN_ALT caps it
        assert np.linalg.norm(v.position_enu()[:2]) < 0.1 and v.position_enu()[2] == 0.0
        assert [e for _, e in v.events if e in ("rtl: climb", "rtl: return", "rtl: land", "rtl: idle")] == \
            ["rtl: climb", "rtl: return", "rtl: land", "rtl: idle"]
    finally:
        c.stop()
        v.stop()


@pytest.mark.slow  # real time, ~10 s: opt-in (`-m slow`)
def test_px4_return_land_delay_descends_holds_then_lands_and_a_mode_change_stops_it():
    params = (("MIS_TAKEOFF_ALT", 1.0), ("RTL_CONE_ANG", 0), ("RTL_RETURN_ALT", 3.0), ("RTL_DESCEND_ALT", 2.0),
              ("RTL_LAND_DELAY", 0.5), ("NAV_MC_ALT_RAD", 0.1), ("LNDMC_TRIG_TIME", 0.3), ("COM_DISARM_LAND", 0.3))
    c, v = rig(autopilot="px4", profile="outdoor", params=params)
    try:
        _px4_take_off(c, v)
        assert c.command(M.MAV_CMD_NAV_RETURN_TO_LAUNCH) == M.MAV_RESULT_ACCEPTED
        zs = []
        assert _wait(lambda: zs.append(v.position_enu()[2]) or not v.armed, 12.0), v.events
        phases = [(t, e) for t, e in v.events if e.startswith("rtl: ") and " at " not in e]
        assert [e for _, e in phases] == ["rtl: climb", "rtl: return", "rtl: descend", "rtl: hold", "rtl: land", "rtl: idle"]
        times = dict((e, t) for t, e in phases)
        assert 0.5 <= times["rtl: land"] - times["rtl: hold"] <= 0.6  # RTL_LAND_DELAY (physics time)
        assert max(zs) == pytest.approx(3.0, abs=0.1)  # RTL_RETURN_ALT (no cone)
        texts = [t for _, t in v.statustexts]
        assert "Returning to launch" in texts and "RTL: start return at 491 m (3 m above destination)" in texts
    finally:
        c.stop()
        v.stop()
    c, v = rig(autopilot="px4", profile="outdoor", params=(("MIS_TAKEOFF_ALT", 1.0), ("RTL_CONE_ANG", 0), ("RTL_RETURN_ALT", 30.0)))
    try:
        _px4_take_off(c, v)
        assert c.command(M.MAV_CMD_NAV_RETURN_TO_LAUNCH) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: v.position_enu()[2] > 2.0, 3.0)  # climbing toward 30 m
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, PX4_MAIN["auto"], 3) == M.MAV_RESULT_ACCEPTED  # Hold
        time.sleep(1.5)  # Hold brakes and settles on where the switch happened
        z = v.position_enu()[2]
        time.sleep(0.5)
        assert v.mode_name == "auto.loiter" and abs(v.position_enu()[2] - z) < 0.05 and z < 4.5  # the climb stopped
        assert not [e for t, e in v.events if e.startswith("rtl: ") and t > v.first_event("mode auto.loiter: commanded")]
    finally:
        c.stop()
        v.stop()


def test_return_climb_into_a_ceiling_is_a_crash_in_the_embedded_world():
    """Indoors under a 3.5 m ceiling (the corridor scene) with a GPS origin: Return climbs to
    RTL_RETURN_ALT as PX4 does, whatever is above, and the world's vehicle hits the ceiling
    (the sim is not kinder than reality: a real RTL indoors does the same)."""
    from onfly.mavlink.sim_world import WorldVehicleModel

    model = WorldVehicleModel.from_scene("corridor", position_m=[6.0, 0.0, 1.5], yaw_rad=0.0)
    assert model.ground_z_m == pytest.approx(0.0, abs=1e-6)
    a, b = memory_link_pair(1, 191, 1, 1)
    params = (("MIS_TAKEOFF_ALT", 1.0), ("RTL_CONE_ANG", 0), ("RTL_RETURN_ALT", 5.0))
    v = SimMavlinkVehicle(b, SimVehicleConfig(heartbeat_period_s=0.2, profile="outdoor", params=params), model=model).start()
    c = Companion(a)
    try:
        _px4_take_off(c, v, 10.0)  # the world's vehicle climbs at 0.6 m/s
        assert c.command(M.MAV_CMD_NAV_RETURN_TO_LAUNCH) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: not v.armed, 15.0), v.events
        assert model.collision is not None and model.collision.object_name == "ceiling"
        assert 3.0 < model.p[2] < 3.5  # stopped under the ceiling's underside (3.5 m), body radius 0.25 m
        assert v.first_event("disarmed: crashed into 'ceiling'") is not None
    finally:
        c.stop()
        v.stop()


# -- SET_POSITION_TARGET_GLOBAL_INT rules (the flights with real clients: test_mavlink_clients.py) --
_ORIGIN = (47.397742, 8.545594, 488.0)  # the outdoor profile's global origin
_POS_ONLY = 0x0DF8  # position + yaw used (velocity, acceleration, yaw rate ignored)


def global_setpoint(c, north_m, east_m, alt_m, frame, mask=_POS_ONLY, yaw=0.0, vel_ned=(0.0, 0.0, 0.0)):
    """Send SET_POSITION_TARGET_GLOBAL_INT for a point ``north_m`` / ``east_m`` from the outdoor origin."""
    lat = _ORIGIN[0] + np.degrees(north_m / 6371000.0)
    lon = _ORIGIN[1] + np.degrees(east_m / (6371000.0 * np.cos(np.radians(_ORIGIN[0]))))
    c.link.send(c.link.mav.set_position_target_global_int_encode(
        0, 1, 1, frame, mask, int(round(lat * 1e7)), int(round(lon * 1e7)), alt_m, *vel_ned, 0, 0, 0, yaw, 0))


def test_px4_global_setpoint_frames_indoors_and_the_relative_altitude_as_the_receiver_computes_it():
    # estimator origin 1 m below the ground: ref_alt 487 m, home (the arming point) 488 m AMSL
    c, v = rig(autopilot="px4", profile="outdoor", estimator_origin_m=(0.0, 0.0, -1.0))
    try:
        global_setpoint(c, 2.0, 1.0, 2.0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)  # disarmed: no home yet
        time.sleep(0.1)
        assert v.setpoints_received == 0  # "home altitude required": dropped
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        global_setpoint(c, 2.0, 1.0, 490.5, M.MAV_FRAME_GLOBAL_INT)  # AMSL
        time.sleep(0.1)
        assert v.setpoints_received == 1
        np.testing.assert_allclose(v._setpoint.p, [1.0, 2.0, 2.5], atol=0.02)
        # z_ned = (home.alt - alt) - ref_alt: 2 m "above home" lands 1 m above the ground here
        global_setpoint(c, 2.0, 1.0, 2.0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
        time.sleep(0.1)
        assert v.setpoints_received == 2
        np.testing.assert_allclose(v._setpoint.p, [1.0, 2.0, 0.0], atol=0.02)
        # above terrain: no distance sensor, so no terrain altitude: dropped silently (no offboard signal)
        global_setpoint(c, 2.0, 1.0, 2.0, M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)
        # the non-INT global frames are not among the receiver's frames: dropped with a message
        global_setpoint(c, 2.0, 1.0, 490.5, M.MAV_FRAME_GLOBAL)
        # a force setpoint
        c.link.send(c.link.mav.set_position_target_global_int_encode(
            0, 1, 1, M.MAV_FRAME_GLOBAL_INT, 0x0E3F, 0, 0, 0, 0, 0, 0, 0, 0, 1.0, 0, 0))
        time.sleep(0.15)
        assert v.setpoints_received == 2
        texts = [t for _, t in v.statustexts]
        assert "SET_POSITION_TARGET_GLOBAL_INT invalid coordinate frame 0" in texts
        assert "SET_POSITION_TARGET_GLOBAL_INT force not supported" in texts
        # velocity only (the position bits set): no global reference needed, per axis as LOCAL_NED
        global_setpoint(c, 0.0, 0.0, 0.0, M.MAV_FRAME_GLOBAL_INT, mask=0x0DC7, vel_ned=(0.5, 0.0, 0.0))
        time.sleep(0.1)
        assert v.setpoints_received == 3 and v._setpoint.kind == "velocity"
        np.testing.assert_allclose(v._setpoint.v, [0.0, 0.5, 0.0], atol=1e-9)
    finally:
        c.stop()
        v.stop()
    # indoors (no global origin): a position setpoint cannot be converted: dropped, so it is no
    # offboard signal and OFFBOARD is refused
    c, v = rig(autopilot="px4")
    try:
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        for _ in range(4):
            global_setpoint(c, 1.0, 0.0, 1.0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
            time.sleep(0.02)
        px4_offboard = (M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_MAIN["offboard"])
        assert c.command(M.MAV_CMD_DO_SET_MODE, *px4_offboard) == M.MAV_RESULT_TEMPORARILY_REJECTED
        assert v.setpoints_received == 0 and v.mode_name != "offboard"
    finally:
        c.stop()
        v.stop()


def test_ardupilot_global_target_type_mask_frames_and_indoors():
    c, v = rig(autopilot="ardupilot", profile="outdoor")
    try:
        global_setpoint(c, 2.0, 0.0, 1.0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)  # not GUIDED: ignored
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, ARDUCOPTER_MODE["guided"]) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0) == M.MAV_RESULT_ACCEPTED
        wait = time.monotonic() + 3.0
        while v.first_event("takeoff complete") is None and time.monotonic() < wait:
            time.sleep(0.02)
        assert v.setpoints_received == 0
        # x/y used but z ignored: ArduCopter ignores the whole position vector -> nothing used -> stop
        global_setpoint(c, 2.0, 0.0, 1.0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mask=_POS_ONLY | M.POSITION_TARGET_TYPEMASK_Z_IGNORE)
        time.sleep(0.05)
        assert v.first_event("guided: input not valid (unsupported type_mask combination)") is not None
        # an unknown frame (LOCAL_NED in a global message) stops; above terrain without terrain data stops
        global_setpoint(c, 2.0, 0.0, 1.0, M.MAV_FRAME_LOCAL_NED)
        global_setpoint(c, 2.0, 0.0, 1.0, M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)
        # position + velocity above terrain: the pos/vel controller has no terrain frame
        global_setpoint(c, 2.0, 0.0, 1.0, M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT, mask=0x0DC0)
        time.sleep(0.1)
        assert v.first_event("guided: input not valid (unknown coordinate frame 1)") is not None
        assert v.first_event("guided: input not valid (no terrain data for an above-terrain target)") is not None
        assert v.first_event("guided: input not valid (pos/vel target above terrain)") is not None
        assert v.setpoints_received == 0 and v._setpoint.kind == "velocity" and not v._setpoint.v.any()
        # a point in MAV_FRAME_GLOBAL (AMSL, non-INT: ArduPilot maps it like GLOBAL_INT) is flown
        global_setpoint(c, 1.0, 0.0, 489.0, M.MAV_FRAME_GLOBAL, yaw=np.pi / 2)  # east (NED yaw)
        time.sleep(0.8)
        assert v.setpoints_received == 1
        np.testing.assert_allclose(v.position_enu(), [0.0, 1.0, 1.0], atol=0.1)
        assert abs(v.model.yaw) < 0.1  # NED 90 deg = ENU 0
    finally:
        c.stop()
        v.stop()
    # indoors: no EKF origin: set_destination returns before changing anything: ignored, target kept
    c, v = rig(autopilot="ardupilot")
    try:
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, ARDUCOPTER_MODE["guided"]) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0.5) == M.MAV_RESULT_ACCEPTED
        time.sleep(0.6)
        global_setpoint(c, 2.0, 0.0, 1.0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
        time.sleep(0.3)
        assert v.setpoints_received == 0
        assert v.first_event("guided: global target ignored (no vector from the EKF origin)") is not None
        np.testing.assert_allclose(v.position_enu(), [0.0, 0.0, 0.5], atol=0.1)
    finally:
        c.stop()
        v.stop()


def _command_to(c, target_system, target_component, cmd, *params, timeout_s=0.4):
    """A COMMAND_LONG to the given target; its ACK result, or None when none comes."""
    n0 = len(c.of_type("COMMAND_ACK"))
    p = list(params) + [0.0] * (7 - len(params))
    c.link.send(c.link.mav.command_long_encode(target_system, target_component, cmd, 0, *p))
    if _wait(lambda: any(a.command == cmd for _, a in c.of_type("COMMAND_ACK")[n0:]), timeout_s):
        return next(a.result for _, a in c.of_type("COMMAND_ACK")[n0:] if a.command == cmd)
    return None


def _home_int(c, x, y, z, frame=M.MAV_FRAME_GLOBAL_INT, param1=0.0):
    n0 = len(c.of_type("COMMAND_ACK"))
    c.link.send(c.link.mav.command_int_encode(1, 1, frame, M.MAV_CMD_DO_SET_HOME, 0, 0, param1, 0, 0, 0, x, y, z))
    assert _wait(lambda: any(a.command == M.MAV_CMD_DO_SET_HOME for _, a in c.of_type("COMMAND_ACK")[n0:]), 1.0)
    return next(a.result for _, a in c.of_type("COMMAND_ACK")[n0:] if a.command == M.MAV_CMD_DO_SET_HOME)


def test_commands_for_another_target_and_do_set_home_rules_px4_and_ardupilot():
    nan = float("nan")
    lat0, lon0, alt0 = 47.397742, 8.545594, 488.0
    dlat = float(np.degrees(10.0 / 6371000.0))  # 10 m north
    c, v = rig(autopilot="px4", profile="outdoor")
    try:
        # evaluate_target_ok: another component, another system and the broadcast system are not answered
        assert _command_to(c, 1, 2, M.MAV_CMD_COMPONENT_ARM_DISARM, 1) is None and not v.armed
        assert _command_to(c, 2, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 1) is None
        assert _command_to(c, 0, 0, M.MAV_CMD_COMPONENT_ARM_DISARM, 1) is None and not v.armed
        assert _command_to(c, 0, 0, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1) == M.MAV_RESULT_ACCEPTED  # broadcast case
        assert _command_to(c, 1, 0, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1) == M.MAV_RESULT_ACCEPTED
        assert v.first_event("command 400 for 1/2 ignored") is not None
        # DO_SET_HOME: NaN lat/lon DENIED, param1 1 = here, else lat/lon/alt (AMSL)
        assert c.command(M.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, nan, nan, nan) == M.MAV_RESULT_DENIED
        assert c.command(M.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, lat0 + dlat, lon0, alt0 + 1.0) == M.MAV_RESULT_ACCEPTED
        np.testing.assert_allclose(v._home, [0.0, 10.0, 1.0], atol=0.25)  # float32 param5/6: ~0.1 m
        assert _home_int(c, int(round((lat0 + 2 * dlat) * 1e7)), int(round(lon0 * 1e7)), alt0,
                         frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) == M.MAV_RESULT_ACCEPTED  # frame not read: AMSL
        np.testing.assert_allclose(v._home, [0.0, 20.0, 0.0], atol=0.02)
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        np.testing.assert_allclose(v._home, [0.0, 20.0, 0.0], atol=0.02)  # manual_home: kept at arming
        assert c.command(M.MAV_CMD_GET_HOME_POSITION) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: any(abs(h.latitude - (lat0 + 2 * dlat) * 1e7) < 2 for _, h in c.of_type("HOME_POSITION")))
        assert c.command(M.MAV_CMD_DO_SET_HOME, 1) == M.MAV_RESULT_ACCEPTED
        np.testing.assert_allclose(v._home, v.position_enu(), atol=0.01)
    finally:
        c.stop()
        v.stop()
    c, v = rig(autopilot="px4")  # indoors: here works, a lat/lon home needs a global reference
    try:
        assert c.command(M.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, lat0, lon0, alt0) == M.MAV_RESULT_TEMPORARILY_REJECTED
        assert c.command(M.MAV_CMD_DO_SET_HOME, 1) == M.MAV_RESULT_ACCEPTED
    finally:
        c.stop()
        v.stop()
    c, v = rig(autopilot="ardupilot", profile="outdoor")
    try:
        # MAVLink_routing: our system, any component, is processed here; another system is not answered
        assert _command_to(c, 1, 2, M.MAV_CMD_DO_SET_MODE, 1, ARDUCOPTER_MODE["guided"]) == M.MAV_RESULT_ACCEPTED
        assert v.mode_name == "guided"
        assert _command_to(c, 0, 0, M.MAV_CMD_DO_CHANGE_SPEED, 1, 2.0) == M.MAV_RESULT_ACCEPTED
        assert _command_to(c, 2, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 1) is None and not v.armed
        # DO_SET_HOME: lat and lon 0 = here (HOME_POSITION sent at once), COMMAND_LONG altitude AMSL,
        # COMMAND_INT in its frame, an unknown frame DENIED
        n_home = len(c.of_type("HOME_POSITION"))
        assert c.command(M.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, 0.0, 0.0, 0.0) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: len(c.of_type("HOME_POSITION")) > n_home)
        assert c.command(M.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, lat0 + dlat, lon0, alt0 + 2.0) == M.MAV_RESULT_ACCEPTED
        np.testing.assert_allclose(v._home, [0.0, 10.0, 2.0], atol=0.25)  # float32 param5/6
        assert _home_int(c, int(round((lat0 + 2 * dlat) * 1e7)), int(round(lon0 * 1e7)), 1.0,
                         frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) == M.MAV_RESULT_ACCEPTED  # 1 m above the old home
        np.testing.assert_allclose(v._home, [0.0, 20.0, 3.0], atol=0.02)
        assert _home_int(c, int(round(lat0 * 1e7)), int(round(lon0 * 1e7)), 0.0, frame=M.MAV_FRAME_LOCAL_NED) == M.MAV_RESULT_DENIED
        h = c.of_type("HOME_POSITION")[-1][1]
        assert abs(h.latitude - (lat0 + 2 * dlat) * 1e7) < 2 and h.altitude == pytest.approx((alt0 + 3.0) * 1000, abs=20)
    finally:
        c.stop()
        v.stop()
    c, v = rig(autopilot="ardupilot")  # indoors: no location, no EKF origin
    try:
        assert c.command(M.MAV_CMD_DO_SET_HOME, 1) == M.MAV_RESULT_FAILED
        assert c.command(M.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, lat0, lon0, alt0) == M.MAV_RESULT_FAILED
    finally:
        c.stop()
        v.stop()


# -- SET_POSITION_TARGET_LOCAL_NED frames and the yaw rate (the flights with real clients: test_mavlink_clients.py) --
_T = M  # type_mask bits
_IGN_POS = _T.POSITION_TARGET_TYPEMASK_X_IGNORE | _T.POSITION_TARGET_TYPEMASK_Y_IGNORE | _T.POSITION_TARGET_TYPEMASK_Z_IGNORE
_IGN_VEL = _T.POSITION_TARGET_TYPEMASK_VX_IGNORE | _T.POSITION_TARGET_TYPEMASK_VY_IGNORE | _T.POSITION_TARGET_TYPEMASK_VZ_IGNORE
_IGN_ACC = _T.POSITION_TARGET_TYPEMASK_AX_IGNORE | _T.POSITION_TARGET_TYPEMASK_AY_IGNORE | _T.POSITION_TARGET_TYPEMASK_AZ_IGNORE
_IGN_YAW, _IGN_RATE = _T.POSITION_TARGET_TYPEMASK_YAW_IGNORE, _T.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE


def local_target(c, frame, ignore, p=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0), a=(0.0, 0.0, 0.0), yaw=0.0, yaw_rate=0.0):
    """Send SET_POSITION_TARGET_LOCAL_NED in ``frame`` with the type_mask ``ignore`` (m, m/s, m/s^2, rad, rad/s)."""
    c.link.send(c.link.mav.set_position_target_local_ned_encode(0, 1, 1, frame, ignore, *p, *v, *a, yaw, yaw_rate))


def test_px4_body_ned_rotates_velocity_by_the_heading_flies_the_yawspeed_and_the_other_frames_are_refused():
    yaw0, est_yaw = 0.4, -0.9  # scene ENU heading; the estimator frame's rotation in the scene
    c, v = rig(autopilot="px4", initial_yaw_rad=yaw0, estimator_yaw_rad=est_yaw)
    try:
        fwd, right = np.array([np.cos(yaw0), np.sin(yaw0), 0.0]), np.array([np.sin(yaw0), -np.cos(yaw0), 0.0])
        # on the ground, level: the acceleration (rotated by the whole attitude) turns with the heading too
        local_target(c, M.MAV_FRAME_BODY_NED, _IGN_POS | _IGN_YAW | _IGN_RATE, p=(9.0, 9.0, 9.0), v=(1.0, 0.5, -0.5), a=(1.0, 0.0, 0.0))
        assert _wait(lambda: v.setpoints_received == 1)
        sp = v._setpoint
        assert sp.p is None  # PX4 never uses a BODY_NED position
        np.testing.assert_allclose(sp.v, 1.0 * fwd + 0.5 * right + [0.0, 0.0, 0.5], atol=1e-9)  # z down -> up
        np.testing.assert_allclose(sp.a, fwd, atol=1e-9)
        # the yaw is absolute (a NED heading in the estimator frame), the yaw rate PX4's yawspeed
        local_target(c, M.MAV_FRAME_BODY_NED, _IGN_POS | _IGN_ACC, yaw=0.0, yaw_rate=0.3)
        assert _wait(lambda: v.setpoints_received == 2)
        assert v._setpoint.yaw == pytest.approx(np.pi / 2 + est_yaw) and v._setpoint.yaw_rate == pytest.approx(-0.3)
        time.sleep(0.35)  # past COM_OF_LOSS_T: the refusals below must not bring the offboard signal back
        local_target(c, M.MAV_FRAME_LOCAL_OFFSET_NED, _IGN_VEL | _IGN_ACC | _IGN_YAW | _IGN_RATE, p=(1.0, 0.0, 0.0))
        local_target(c, M.MAV_FRAME_BODY_OFFSET_NED, _IGN_POS | _IGN_ACC | _IGN_YAW | _IGN_RATE, v=(1.0, 0.0, 0.0))
        local_target(c, M.MAV_FRAME_BODY_NED, _IGN_VEL | _IGN_ACC | _IGN_YAW | _IGN_RATE, p=(1.0, 0.0, -1.0))  # position only
        local_target(c, M.MAV_FRAME_BODY_NED, _IGN_POS | _T.POSITION_TARGET_TYPEMASK_VZ_IGNORE | _IGN_ACC, v=(1.0, 0.0, 0.0))
        local_target(c, M.MAV_FRAME_LOCAL_NED, _IGN_POS | _IGN_VEL | _T.POSITION_TARGET_TYPEMASK_FORCE_SET, a=(1.0, 0.0, 0.0))
        assert _wait(lambda: len(v.statustexts) >= 5)
        texts = [t for _, t in v.statustexts]
        assert "SET_POSITION_TARGET_LOCAL_NED coordinate frame 7 unsupported" in texts
        assert "SET_POSITION_TARGET_LOCAL_NED coordinate frame 9 unsupported" in texts
        assert texts.count("SET_POSITION_TARGET_LOCAL_NED invalid") == 2  # one ignored axis ignores the body velocity
        assert "SET_POSITION_TARGET_LOCAL_NED force not supported" in texts
        assert v.setpoints_received == 2
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, PX4_MAIN["offboard"]) == M.MAV_RESULT_TEMPORARILY_REJECTED
        # flown: climb at 1 m/s, turning clockwise at 0.5 rad/s with the yaw NaN (PositionControl: yaw held, yawspeed fed forward)
        local_target(c, M.MAV_FRAME_BODY_NED, _IGN_POS | _IGN_ACC | _IGN_YAW, v=(0.0, 0.0, -1.0), yaw_rate=0.5)
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, PX4_MAIN["offboard"]) == M.MAV_RESULT_ACCEPTED
        for _ in range(8):
            local_target(c, M.MAV_FRAME_BODY_NED, _IGN_POS | _IGN_ACC | _IGN_YAW, v=(0.0, 0.0, -1.0), yaw_rate=0.5)
            time.sleep(0.05)
        assert v.model.yaw_rate == pytest.approx(-0.5) and v.velocity_enu()[2] == pytest.approx(1.0, abs=0.05)
        n0 = len(c.of_type("POSITION_TARGET_LOCAL_NED"))
        assert _wait(lambda: len(c.of_type("POSITION_TARGET_LOCAL_NED")) > n0)
        pt = c.of_type("POSITION_TARGET_LOCAL_NED")[-1][1]  # what PX4 reports it tracks
        # PositionControl::update: a yaw not commanded is the current one (no ignore bit); the
        # velocity and acceleration are the controller's setpoints; the position stays NaN
        assert pt.type_mask == _IGN_POS and all(math.isnan(x) for x in (pt.x, pt.y, pt.z))
        assert pt.yaw_rate == pytest.approx(0.5)
        now_ned = frames.yaw_ned_from_enu(v.model.yaw - est_yaw)
        assert abs(wrap_angle(pt.yaw - now_ned)) < 0.1  # 0.5 rad/s between the report and now
        assert (pt.vx, pt.vy, pt.vz) == pytest.approx((0.0, 0.0, -1.0), abs=1e-6)
        assert all(math.isfinite(x) for x in (pt.afx, pt.afy, pt.afz))
        # a position alone: the velocity the position loop flies toward it, the yaw held, no rate
        here = frames.ned_from_enu(v.local_from_scene(v.position_enu()))
        goal = here + np.array([3.0, 0.0, 0.0])
        for _ in range(6):
            local_target(c, M.MAV_FRAME_LOCAL_NED, _IGN_VEL | _IGN_ACC | _IGN_YAW | _IGN_RATE, p=tuple(goal))
            time.sleep(0.05)
        n0 = len(c.of_type("POSITION_TARGET_LOCAL_NED"))
        assert _wait(lambda: len(c.of_type("POSITION_TARGET_LOCAL_NED")) > n0)
        pt = c.of_type("POSITION_TARGET_LOCAL_NED")[-1][1]
        assert pt.type_mask == 0 and pt.yaw_rate == 0.0
        np.testing.assert_allclose((pt.x, pt.y, pt.z), goal, atol=1e-4)
        assert pt.vx > 0.1 and np.hypot(pt.vx, pt.vy) <= v.c.v_max_mps + 1e-6  # toward the goal (north)
    finally:
        c.stop()
        v.stop()


def test_ardupilot_guided_targets_in_body_frames_and_the_yaw_rate_as_autoyaw_flies_them():
    c, v = rig(autopilot="ardupilot", initial_yaw_rad=0.3, estimator_yaw_rad=0.6)
    pos_rate = _IGN_VEL | _IGN_ACC | _IGN_YAW  # position and yaw rate used
    try:
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, ARDUCOPTER_MODE["guided"]) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0) == M.MAV_RESULT_ACCEPTED
        assert _wait(lambda: v.first_event("takeoff complete") is not None)
        here = v.position_enu()
        # BODY_NED positions are offsets from here too (every frame but LOCAL_NED), x/y along the heading
        local_target(c, M.MAV_FRAME_BODY_NED, _IGN_VEL | _IGN_ACC | _IGN_YAW | _IGN_RATE, p=(1.0, 0.0, 0.0))
        assert _wait(lambda: v.setpoints_received == 1)
        np.testing.assert_allclose(v._setpoint.p, here + [np.cos(0.3), np.sin(0.3), 0.0], atol=1e-6)
        hold_ned = frames.ned_from_enu(v.local_from_scene(here))
        # AutoYaw RATE: a rate alone turns at it (0.5 rad/s clockwise), above ATC_SLEW_YAW (60 deg/s) at that
        local_target(c, M.MAV_FRAME_LOCAL_NED, pos_rate, p=hold_ned, yaw_rate=0.5)
        time.sleep(0.3)
        assert v.model.yaw_rate == pytest.approx(-0.5)
        local_target(c, M.MAV_FRAME_LOCAL_NED, pos_rate, p=hold_ned, yaw_rate=2.0)
        time.sleep(0.3)
        assert v.model.yaw_rate == pytest.approx(-np.radians(60.0))
        # no target for GUID_TIMEOUT (0.5 s here): "stop rotating", even under a position target
        assert _wait(lambda: v.first_event("guided timeout") is not None, 1.0)
        time.sleep(0.05)
        assert v.model.yaw_rate == 0.0 and np.linalg.norm(v.position_enu() - here) < 0.05
        # AutoYaw ANGLE_RATE: yaw and rate given: the heading target advances at the rate from the given yaw
        heading_ned = np.pi / 2 - (v.model.yaw - 0.6)  # where it points, NED in the estimator frame
        yaw_start = v.model.yaw
        local_target(c, M.MAV_FRAME_LOCAL_NED, _IGN_VEL | _IGN_ACC, p=hold_ned, yaw=heading_ned, yaw_rate=0.4)
        t0 = time.monotonic()
        time.sleep(0.4)
        turned = -np.arctan2(np.sin(v.model.yaw - yaw_start), np.cos(v.model.yaw - yaw_start))
        assert turned == pytest.approx(0.4 * (time.monotonic() - t0), abs=0.03)
        assert _wait(lambda: v.model.yaw_rate == 0.0, 1.0)  # GUID_TIMEOUT again
        # a relative yaw (the body frames): 1.2 rad clockwise of AutoYaw's angle, slewed at ATC_SLEW_YAW, the rate unused
        yaw_held = v.model.yaw
        local_target(c, M.MAV_FRAME_BODY_OFFSET_NED, _IGN_VEL | _IGN_ACC, yaw=1.2, yaw_rate=1.0)
        time.sleep(0.15)
        assert v.model.yaw_rate == pytest.approx(-np.radians(60.0)) and v._target.yaw_rate is None
        assert np.sin(v._target.yaw - (yaw_held - 1.2)) == pytest.approx(0.0, abs=1e-6)
        assert _wait(lambda: abs(np.sin(v.model.yaw - (yaw_held - 1.2))) < 0.05, 2.0)
        assert np.linalg.norm(v.position_enu() - here) < 0.05  # an offset of 0: held where it was
    finally:
        c.stop()
        v.stop()


def test_ardupilot_local_target_refusals_stop_or_ignore_as_the_source_does():
    c, v = rig(autopilot="ardupilot")
    none = _IGN_POS | _IGN_VEL | _IGN_ACC | _IGN_YAW | _IGN_RATE
    try:
        local_target(c, M.MAV_FRAME_BODY_NED, none & ~_IGN_VEL, v=(1.0, 0.0, 0.0))  # STABILIZE: not in_guided_mode
        time.sleep(0.05)
        assert v.setpoints_received == 0 and not [e for _, e in v.events if e.startswith("guided")]
        assert c.command(M.MAV_CMD_DO_SET_MODE, 1, ARDUCOPTER_MODE["guided"]) == M.MAV_RESULT_ACCEPTED
        local_target(c, M.MAV_FRAME_BODY_FRD, none & ~_IGN_VEL, v=(1.0, 0.0, 0.0))
        local_target(c, M.MAV_FRAME_LOCAL_NED, none & ~_IGN_POS & ~_IGN_ACC)  # position + acceleration without velocity
        local_target(c, M.MAV_FRAME_LOCAL_NED, none)  # nothing used
        local_target(c, M.MAV_FRAME_LOCAL_NED, none & ~_IGN_ACC | _T.POSITION_TARGET_TYPEMASK_FORCE_SET, a=(1.0, 0.0, 0.0))
        local_target(c, M.MAV_FRAME_BODY_NED, none & ~_IGN_VEL, v=(2000.0, 0.0, 0.0))
        time.sleep(0.05)
        v.set_position_valid(False)
        local_target(c, M.MAV_FRAME_LOCAL_OFFSET_NED, none & ~_IGN_POS, p=(1.0, 0.0, 0.0))
        time.sleep(0.05)
        stops = [e for _, e in v.events if e.startswith("guided: input not valid")]
        assert stops == ["guided: input not valid (unsupported coordinate frame 12): stop",
                         "guided: input not valid (unsupported type_mask combination): stop",
                         "guided: input not valid (unsupported type_mask combination): stop",
                         "guided: input not valid (force setpoint): stop",
                         "guided: input not valid (velocity not sane): stop",
                         "guided: input not valid (no position estimate for an offset target): stop"]
        assert v.setpoints_received == 0 and [t for _, t in v.statustexts] == ["Mode guided"]  # the stops are silent
    finally:
        c.stop()
        v.stop()
