"""Bad input on the bridge's port: random bytes, corrupted packets, unknown messages, foreign
system/component ids and a flood. The bridge must not crash, must not believe foreign state,
and must not command motion because of any of it. Senders are bounded in count and time and
talk to 127.0.0.1 only."""

import socket
import time

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from onfly.mavlink.autopilot import OffboardConfig, PX4_MAIN, Px4Offboard, px4_custom_mode
from onfly.mavlink.bridge import BridgeConfig, MavlinkBridge, SetpointKind
from onfly.mavlink.failsafe import FailsafeCause
from onfly.mavlink.link import MavlinkLink, memory_link_pair, mavlink2
from onfly.mavlink.sim_vehicle import SimMavlinkVehicle, SimVehicleConfig
from onfly.mavlink.state import StateReader

M = mavlink2


def hostile_packets(rng, n_random=600):
    """Datagrams an attacker (or a noisy radio) might send: random bytes, foreign-id MAVLink,
    wrong-component MAVLink, unknown messages, and bit-flipped copies of valid vehicle packets."""
    foreign = M.MAVLink(None, srcSystem=42, srcComponent=1)
    wrong_comp = M.MAVLink(None, srcSystem=1, srcComponent=99)
    vehicle_like = M.MAVLink(None, srcSystem=1, srcComponent=1)
    valid = [
        foreign.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, M.MAV_MODE_FLAG_SAFETY_ARMED | 1, px4_custom_mode(PX4_MAIN["offboard"]), 4).pack(foreign),
        foreign.local_position_ned_encode(10, 900.0, -900.0, -500.0, 50, 50, 50).pack(foreign),
        foreign.command_ack_encode(M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_RESULT_ACCEPTED, 0, 0, 1, 191).pack(foreign),
        foreign.set_position_target_local_ned_encode(0, 1, 1, M.MAV_FRAME_LOCAL_NED, 0, 500, 500, -500, 0, 0, 0, 0, 0, 0, 0, 0).pack(foreign),
        foreign.command_long_encode(1, 191, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0).pack(foreign),
        wrong_comp.local_position_ned_encode(10, 700.0, 700.0, -700.0, 0, 0, 0).pack(wrong_comp),
        wrong_comp.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, 0, 0, 4).pack(wrong_comp),
        vehicle_like.vfr_hud_encode(1, 2, 3, 4, 5, 6).pack(vehicle_like),  # known, unused
    ]
    out = []
    for i in range(n_random):
        kind = i % 4
        if kind == 0:
            out.append(rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
        elif kind == 1:
            out.append(valid[int(rng.integers(len(valid)))])
        elif kind == 2:
            # a valid-looking vehicle position with one flipped bit (CRC must reject it)
            buf = bytearray(vehicle_like.local_position_ned_encode(10 + i, 800.0, 800.0, -800.0, 0, 0, 0).pack(vehicle_like))
            j = int(rng.integers(1, len(buf)))
            buf[j] ^= 1 << int(rng.integers(8))
            out.append(bytes(buf))
        else:
            # unknown message id (MAVLink 2 header with an id no dialect defines) + noise
            out.append(bytes([0xFD, 4, 0, 0, 7, 1, 1, 0xEF, 0xBE, 0xAD]) + rng.integers(0, 256, size=6, dtype=np.uint8).tobytes())
    return out


def loopback(autopilot="px4"):
    bridge_link = MavlinkLink("udpin:127.0.0.1:0", 1, 191)
    bridge_link.connect()
    port = bridge_link.local_address[1]
    vehicle = SimMavlinkVehicle(
        MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1),
        SimVehicleConfig(autopilot=autopilot, heartbeat_period_s=0.2, offboard_loss_timeout_s=0.5),
    ).start()
    bridge = MavlinkBridge(bridge_link, BridgeConfig()).start()
    bridge.wait_for_vehicle(3.0)
    bridge.wait_for_state(3.0)
    return bridge, vehicle, port


def flood(port, packets, duration_s, max_count, rate_pps=5000.0):
    """Send ``packets`` round-robin to 127.0.0.1:port, ~``rate_pps`` datagrams per second (in bursts
    of 50), for at most ``duration_s`` seconds and ``max_count`` datagrams. 5000 per second is
    ~100 times the vehicle's own telemetry rate."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent, t0 = 0, time.monotonic()
    try:
        while sent < max_count and time.monotonic() - t0 < duration_s:
            sock.sendto(packets[sent % len(packets)], ("127.0.0.1", port))
            sent += 1
            if sent % 50 == 0:
                time.sleep(max(0.0, t0 + sent / rate_pps - time.monotonic()))
    finally:
        sock.close()
    return sent


def test_idle_bridge_under_hostile_traffic_commands_nothing_and_keeps_true_state():
    bridge, vehicle, port = loopback()
    try:
        rng = np.random.default_rng(0)
        sent = flood(port, hostile_packets(rng), duration_s=0.8, max_count=4000)
        assert sent >= 600
        time.sleep(0.3)
        assert bridge.running and bridge.errors == []
        assert vehicle.setpoints_received == 0 and not vehicle.armed  # no motion was commanded
        assert bridge.sent.maxlen and len(bridge.sent) == 0
        st = bridge.state()
        assert np.linalg.norm(st.p) < 0.05  # the real vehicle sits at the origin; no 700-900 m ghosts
        status = bridge.status()
        assert status.custom_mode == px4_custom_mode(4, 3) and not status.armed  # not the fake OFFBOARD
        assert bridge.link.stats.bad_in > 0 and bridge.reader.counts["foreign"] > 0
        assert bridge.failsafe.events == [], bridge.failsafe.events
    finally:
        bridge.stop()
        vehicle.stop()


def test_flood_during_offboard_flight_keeps_the_stream_steady_and_the_state_true():
    bridge, vehicle, port = loopback()
    try:
        Px4Offboard(bridge, OffboardConfig(prestream_s=0.4)).engage()
        t0 = time.monotonic()
        rng = np.random.default_rng(1)
        sent = flood(port, hostile_packets(rng, 400), duration_s=1.0, max_count=8000)
        time.sleep(0.5)
        t_end = time.monotonic()
        assert sent >= 400
        assert vehicle.mode_name == "offboard"
        sp_t = np.array([t for t in vehicle.setpoint_times if t >= t0])
        assert len(sp_t) / (t_end - t0) >= 15.0 and np.max(np.diff(sp_t)) < 0.3
        assert bridge.failsafe.first_event(FailsafeCause.LINK_LOST) is None, bridge.failsafe.events
        sent_sp = [s for s in bridge.sent]
        assert all(s.kind is SetpointKind.HOLD for s in sent_sp)
        assert max(np.linalg.norm(s.p) for s in sent_sp) < 0.05  # held at the true origin
        assert not bridge.released and bridge.running
    finally:
        bridge.stop()
        vehicle.stop()


def test_memory_link_garbage_is_counted_not_raised():
    a, b = memory_link_pair(1, 191, 1, 1)
    bridge = MavlinkBridge(a, BridgeConfig()).start()
    b.connect()
    rng = np.random.default_rng(2)
    for pkt in hostile_packets(rng, 400):
        a.inject_bytes(pkt)
    # Telemetry keeps flowing, as on a real link: a garbage frame may swallow a few valid bytes
    # (the parser waits for the length a corrupt header claimed), never the stream.
    for k in range(10):
        b.send(b.mav.heartbeat_encode(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, 1, 0, 3))
        b.send(b.mav.local_position_ned_encode(5 + k, 1.0, 2.0, -3.0, 0, 0, 0))
        b.send(b.mav.attitude_encode(5 + k, 0, 0, 0, 0, 0, 0))
    try:
        bridge.wait_for_vehicle(2.0)
        st = bridge.wait_for_state(2.0)
        np.testing.assert_allclose(st.p, [2.0, 1.0, 3.0], atol=1e-6)
        assert a.stats.bad_in > 50 and bridge.running and bridge.errors == []
    finally:
        bridge.stop()


_f32 = st.floats(width=32, allow_nan=True, allow_infinity=True)


@settings(max_examples=150, derandomize=True, suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(
    kind=st.sampled_from(["pos", "att", "quat"]),
    vals=st.lists(_f32, min_size=7, max_size=7),
    tb=st.integers(0, 2**32 - 1),
)
def test_state_reader_never_raises_and_never_holds_non_finite_state(kind, vals, tb):
    reader = StateReader(clock=lambda: 1.0)
    enc = M.MAVLink(None, srcSystem=1, srcComponent=1)
    dec = M.MAVLink(None)
    seed = [enc.local_position_ned_encode(0, 0, 0, 0, 0, 0, 0), enc.attitude_encode(0, 0, 0, 0, 0, 0, 0)]
    for m in seed:
        reader.handle(dec.parse_char(m.pack(enc)))
    if kind == "pos":
        msg = enc.local_position_ned_encode(tb, *vals[:6])
    elif kind == "att":
        msg = enc.attitude_encode(tb, *vals[:6])
    else:
        msg = enc.attitude_quaternion_encode(tb, *vals[:4], *vals[4:7])
    reader.handle(dec.parse_char(msg.pack(enc)))
    s = reader.state()
    assert s is not None and np.all(np.isfinite(s.p)) and np.all(np.isfinite(s.v)) and np.isfinite(s.yaw)


def test_a_udpin_read_never_runs_while_another_thread_sends():
    """pymavlink's udpin read adds each new peer to the set its write iterates; a read on the
    bridge's reader thread during a send on its setpoint thread raised "Set changed size during
    iteration" in the sender (the setpoint stream stopped and PX4 left OFFBOARD). Reads and
    sends of one link are serialized."""
    link = MavlinkLink("udpin:127.0.0.1:0", 1, 191)
    link.connect()
    try:
        port = link.local_address[1]
        conn = link._conn
        held = []
        real_recv, real_write = conn.recv_msg, conn.write
        conn.recv_msg = lambda: (held.append(("read", link._send_lock.locked())), real_recv())[1]
        conn.write = lambda buf: (held.append(("write", link._send_lock.locked())), real_write(buf))[1]
        peers = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
        hb = link.mav.heartbeat_encode(6, 8, 0, 0, 0)
        for s in peers:  # three peers, each new to the server's client set
            s.sendto(hb.pack(link.mav), ("127.0.0.1", port))
        time.sleep(0.05)
        while link.recv(0.0) is not None:
            pass
        link.send(hb)
        assert {k for k, _ in held} == {"read", "write"}
        assert all(locked for _, locked in held)
        assert len(conn.clients) == 3
        for s in peers:
            s.close()
    finally:
        link.close()
