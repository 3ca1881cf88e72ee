"""End to end on loopback: `onfly sim-vehicle` (the embedded world as a PX4 vehicle, its camera
on TCP) and `onfly fly` (bridge, OnFly pilot, simulated VLM) fly a benchmark task: take-off,
offboard, flight, STOP, hold.

- default: both commands in one process on threads (same code paths, UDP and TCP loopback),
  a short variant of urban_block-o01 that starts 3.7 m from the goal point;
- slow: two processes fly the whole urban_block-o01 and must match `onfly run` (the in-process
  benchmark) in success for the same task and seed.
"""

import argparse
import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from onfly.bench.tasks import load_tasks
from onfly.commands import fly as fly_cmd
from onfly.commands import sim_vehicle as sim_vehicle_cmd

TASK = "urban_block-o01"


def free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def parse(module, argv):
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return parser.parse_args(argv)


def goal_distance(position) -> float:
    task = next(t for t in load_tasks() if t.task_id == TASK)
    return float(task.goal_region.distance(np.asarray(position, float)[None])[0])


def _in_process_flight(tmp_path, autopilot, on_finish):
    """sim-vehicle (a thread) + fly on loopback, the short variant of the task; returns
    (fly rc, fly summary, vehicle ground truth)."""
    mav, cam = free_port(), free_port(socket.SOCK_STREAM)
    vehicle_json, fly_json = tmp_path / "vehicle.json", tmp_path / "fly.json"
    vehicle_args = parse(sim_vehicle_cmd, [
        "--mavlink", f"udpin:127.0.0.1:{mav}", "--autopilot", autopilot, "--task", TASK, "--start", "2.2", "-21.5", "75",
        "--camera", f"tcp://127.0.0.1:{cam}", "--duration-s", "120", "--json", str(vehicle_json),
    ])
    stop = threading.Event()
    vehicle = threading.Thread(target=sim_vehicle_cmd.run, args=(vehicle_args,), kwargs={"stop": stop}, daemon=True)
    vehicle.start()
    try:
        rc = fly_cmd.run(parse(fly_cmd, [
            "--connect", f"udpout:127.0.0.1:{mav}", "--autopilot", autopilot, "--camera", f"tcp://127.0.0.1:{cam}", "--task", TASK,
            "--start", "2.2", "-21.5", "75", "--vlm", "sim:perfect", "--hold-s", "0.5", "--time-limit-s", "40",
            "--on-finish", on_finish, "--json", str(fly_json), "--log", str(tmp_path / "log"), "--rrd", str(tmp_path / "flight.rrd"),
        ]))
        time.sleep(1.5)  # past PX4's COM_OF_LOSS_T: a hand-over that leaned on the loss failsafe would show
    finally:
        stop.set()
        vehicle.join(10.0)
    return rc, json.loads(fly_json.read_text()), json.loads(vehicle_json.read_text())


def _check_landed_flight(rc, summary, truth, landing_mode):
    kinds = [e["kind"] for e in summary["events"]]
    print(f"short {TASK}: end {summary['end_reason']}, flight {summary['flight_time_s']:.1f} s, NE "
          f"{summary['metrics']['navigation_error_m']:.2f} m, landing {[e for e in summary['events'] if e['kind'].startswith('land')]}")
    assert rc == 0 and summary["end_reason"] == "finished" and summary["finished"]
    order = ["world_anchored", "engaged", "begin", "pilot_finished", "hold", "land_site", "land", "landed"]
    assert [k for k in kinds if k in order] == order
    assert summary["metrics"]["success"] and summary["metrics"]["navigation_error_m"] < 5.0 and not summary["metrics"]["collided"]
    assert summary["landed"] and not summary["crashed"]
    # the vehicle's ground truth: no collision, landed on the ground and disarmed by its own land detector
    assert truth["world"]["collision"] is None and truth["world"]["out_of_bounds_s"] is None
    texts = [e["text"] for e in truth["vehicle_events"]]
    assert f"mode {landing_mode}: NAV_LAND" in texts and texts[-1] == "disarmed: landed"
    assert abs(truth["world"]["position_m"][2] - truth["trace_t_x_y_z"][0][3]) < 0.05  # back on the take-off ground
    # a commanded landing is a hand-over, not a takeover; no failsafe is active at the end
    assert not any(f["cause"] == "pilot_takeover" for f in summary["failsafes"])
    assert not [e for e in summary["events"] if e["kind"] == "takeover"]
    # one time base: every event and failsafe on the loop clock, relative to the mission start
    times = [e["t_s"] for e in summary["events"]]
    assert times == sorted(times) and all(-60.0 < t < 120.0 for t in times + [f["t_s"] for f in summary["failsafes"]])


@pytest.mark.slow
def test_in_process_px4_flight_lands_on_clear_ground_and_leaves_a_replayable_record(tmp_path, capsys):
    from onfly.cli import main

    rc, summary, truth = _in_process_flight(tmp_path, "px4", "land")
    _check_landed_flight(rc, summary, truth, "auto.land")
    assert (tmp_path / "flight.rrd").stat().st_size > 10_000
    # the flight's OnFly log replays, exports to a ROS 2 bag (MCAP) that bag-info reads and replay reads too
    assert main(["replay", str(tmp_path / "log"), "--json", str(tmp_path / "replay.json")]) == 0
    rep = json.loads((tmp_path / "replay.json").read_text())
    # frames posed in the flight's world frame agree with their own depth: the logged camera path
    # never enters an obstacle of the map the replay builds from the log
    assert rep["frames"] == rep["frames_read"] > 5 and rep["path_clearance_min_m"] > 0.2
    assert main(["export", str(tmp_path / "log"), "--out", str(tmp_path / "bag"), "--summary", str(tmp_path / "fly.json")]) == 0
    capsys.readouterr()
    assert main(["bag-info", str(tmp_path / "bag"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    counts = {t["name"]: t["count"] for t in info["topics"]}
    assert counts["/camera/color/image_raw"] == counts["/camera/depth/image_raw"] == counts["/camera/pose"] == rep["frames"]
    assert counts["/vehicle/pose"] == len(summary["trace_t_x_y_z"]) and counts["/onfly/events"] > len(summary["events"]) // 2


@pytest.mark.slow
def test_in_process_ardupilot_flight_lands_on_clear_ground(tmp_path):
    rc, summary, truth = _in_process_flight(tmp_path, "ardupilot", "land")
    _check_landed_flight(rc, summary, truth, "land")


@pytest.mark.slow
def test_in_process_ardupilot_hold_is_a_position_target_that_outlives_guid_timeout(tmp_path):
    rc, summary, truth = _in_process_flight(tmp_path, "ardupilot", "hold")
    assert rc == 0 and summary["end_reason"] == "finished" and summary["events"][-1]["kind"] == "handover_hold"
    texts = [e["text"] for e in truth["vehicle_events"]]
    assert not [t for t in texts if t.startswith(("guided timeout", "mode"))][1:]  # stayed in GUIDED, no timeout
    assert truth["world"]["collision"] is None


def _run_benchmark_reference(tmp_path, seed):
    out = tmp_path / "run.json"
    subprocess.run(
        [sys.executable, "-c", "import sys; from onfly.cli import main; sys.exit(main(sys.argv[1:]))",
         "run", "--task", TASK, "--vlm", "sim:perfect", "--seed", str(seed), "--no-rrd", "--json", str(out)],
        check=True, capture_output=True, timeout=300,
    )
    return json.loads(out.read_text())


@pytest.mark.slow
@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_two_processes_fly_land_and_leave_a_record_as_the_docs_say(tmp_path, autopilot):
    """docs/flight.md's two-process flight (free ports instead of 14550 / 5600): the whole task,
    the benchmark's success, a landing on clear ground, then replay / export / bag-info."""
    seed = 0
    mav, cam = free_port(), free_port(socket.SOCK_STREAM)
    vehicle_json, fly_json, log_dir = tmp_path / "vehicle.json", tmp_path / "fly.json", tmp_path / "flight-log"
    entry = [sys.executable, "-c", "import sys; from onfly.cli import main; sys.exit(main(sys.argv[1:]))"]
    vehicle = subprocess.Popen(
        entry + ["sim-vehicle", "--mavlink", f"udpin:127.0.0.1:{mav}", "--autopilot", autopilot, "--task", TASK,
                 "--camera", f"tcp://127.0.0.1:{cam}", "--until-landed", "--json", str(vehicle_json)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        t0 = time.monotonic()
        fly = subprocess.run(
            entry + ["fly", "--connect", f"udpout:127.0.0.1:{mav}", "--autopilot", autopilot, "--camera", f"tcp://127.0.0.1:{cam}",
                     "--task", TASK, "--vlm", "sim:perfect", "--seed", str(seed), "--on-finish", "land",
                     "--log", str(log_dir), "--rrd", str(tmp_path / "flight.rrd"), "--json", str(fly_json)],
            capture_output=True, text=True, timeout=300,
        )
        wall_s = time.monotonic() - t0
        vehicle_out, _ = vehicle.communicate(timeout=30)  # --until-landed: it exits by itself after the disarm
    finally:
        if vehicle.poll() is None:
            vehicle.send_signal(signal.SIGINT)
            vehicle.communicate(timeout=20)
    assert fly.returncode == 0, fly.stderr[-3000:]
    summary = json.loads(fly_json.read_text())
    truth = json.loads(vehicle_json.read_text())
    reference = _run_benchmark_reference(tmp_path, seed)
    m, ref = summary["metrics"], reference["metrics"]
    print(f"\n{TASK} {autopilot} seed {seed}: two processes success {m['success']} flight {m['flight_time_s']:.1f} s NE "
          f"{m['navigation_error_m']:.2f} m (wall {wall_s:.1f} s); onfly run success {ref['success']} flight "
          f"{ref['flight_time_s']:.1f} s NE {ref['navigation_error_m']:.2f} m")
    assert m["success"] == ref["success"] is True
    assert abs(m["flight_time_s"] - ref["flight_time_s"]) < 5.0
    assert truth["world"]["collision"] is None, truth["world"]
    assert summary["landed"] and not summary["crashed"] and "landed and disarmed: exiting" in vehicle_out
    assert vehicle.returncode == 0
    for argv in (["replay", str(log_dir)], ["export", str(log_dir), "--out", str(tmp_path / "flight.mcap")],
                 ["bag-info", str(tmp_path / "flight.mcap")]):
        out = subprocess.run(entry + argv, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
    assert "/camera/pose" in out.stdout and "sensor_msgs/msg/Image" in out.stdout


def test_fly_and_sim_vehicle_refuse_bad_input_with_one_line_errors():
    from onfly.cli import CliError

    port = free_port()
    base = ["--connect", f"udpout:127.0.0.1:{port}"]
    with pytest.raises(CliError, match="give --instruction TEXT or --task ID"):
        fly_cmd.run(parse(fly_cmd, base))
    with pytest.raises(CliError, match="no task 'urban_block-x99'"):
        fly_cmd.run(parse(fly_cmd, base + ["--task", "urban_block-x99"]))
    with pytest.raises(CliError, match="unsupported camera URL 'udp://127.0.0.1:5'"):
        fly_cmd.run(parse(fly_cmd, base + ["--instruction", "go", "--camera", "udp://127.0.0.1:5"]))
    with pytest.raises(CliError, match="cannot open the autopilot link"):
        fly_cmd.run(parse(fly_cmd, ["--connect", "bogus:1", "--instruction", "go"]))
    with pytest.raises(ValueError, match="unknown simulated-VLM preset"):
        fly_cmd.run(parse(fly_cmd, base + ["--instruction", "go", "--vlm", "sim:clairvoyant"]))
    with pytest.raises(CliError, match="--camera needs --scene or --task"):
        sim_vehicle_cmd.run(parse(sim_vehicle_cmd, ["--camera", "tcp://127.0.0.1:5600"]))
    with pytest.raises(CliError, match="task urban_block-o01 is in scene 'urban_block', not 'villa'"):
        sim_vehicle_cmd.run(parse(sim_vehicle_cmd, ["--task", TASK, "--scene", "villa"]))
    with pytest.raises(CliError, match="--volume: flight volume '1,2,3': expected six numbers"):
        fly_cmd.run(parse(fly_cmd, base + ["--instruction", "go", "--volume", "1,2,3"]))
    with pytest.raises(CliError, match="--volume: flight volume needs min < max"):
        fly_cmd.run(parse(fly_cmd, base + ["--instruction", "go", "--volume", "0,0,0,5,5,-1"]))
    with pytest.raises(CliError, match="already exists; choose a new folder"):
        fly_cmd.run(parse(fly_cmd, base + ["--instruction", "go", "--log", str(Path(__file__).parent)]))
    with pytest.raises(CliError, match="unknown px4 parameter 'COM_NOPE'"):
        sim_vehicle_cmd.run(parse(sim_vehicle_cmd, ["--param", "COM_NOPE=1", "--duration-s", "0.1"]))
    with pytest.raises(CliError, match="--param must look like NAME=NUMBER"):
        sim_vehicle_cmd.run(parse(sim_vehicle_cmd, ["--param", "COM_OBL_RC_ACT", "--duration-s", "0.1"]))


def test_a_second_sim_vehicle_on_a_busy_udp_port_is_a_one_line_error(capsys):
    from onfly.cli import main

    port = free_port()
    stop = threading.Event()
    first = threading.Thread(target=sim_vehicle_cmd.run, args=(parse(sim_vehicle_cmd, ["--mavlink", f"udpin:127.0.0.1:{port}", "--duration-s", "5"]),),
                             kwargs={"stop": stop}, daemon=True)
    first.start()
    try:
        time.sleep(0.5)
        assert main(["sim-vehicle", "--mavlink", f"udpin:127.0.0.1:{port}", "--duration-s", "1"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"UDP port {port} is busy" in err[0]
    finally:
        stop.set()
        first.join(5)


def test_fly_volume_from_the_flag_or_the_config_reaches_the_pilot(tmp_path, monkeypatch):
    from onfly.cli import CliError
    import onfly.pilot

    cfg = tmp_path / "fly.toml"
    cfg.write_text('volume = [-5, -5, 0, 20, 10, 4]\n[pilot]\n')
    args = parse(fly_cmd, ["--connect", "udpout:127.0.0.1:9", "--instruction", "go", "--config", str(cfg)])
    vol = fly_cmd._volume(args)
    np.testing.assert_allclose(vol.min_m, [-5, -5, 0])
    np.testing.assert_allclose(vol.max_m, [20, 10, 4])
    args = parse(fly_cmd, ["--connect", "udpout:127.0.0.1:9", "--instruction", "go", "--config", str(cfg), "--volume", "0,0,0,1,1,1"])
    np.testing.assert_allclose(fly_cmd._volume(args).max_m, [1, 1, 1])  # the flag wins
    seen = {}

    class Stop(Exception):
        pass

    def fake_pilot(config, backend, runtime, volume=None):
        seen["volume"] = volume
        raise Stop

    monkeypatch.setattr(onfly.pilot, "OnFlyPilot", fake_pilot)
    with pytest.raises(Stop):
        fly_cmd.run(parse(fly_cmd, ["--connect", "udpout:127.0.0.1:9", "--instruction", "go", "--volume=-1,-2,0,3,4,2.5"]))
    np.testing.assert_allclose(seen["volume"].min_m, [-1, -2, 0])
    np.testing.assert_allclose(seen["volume"].max_m, [3, 4, 2.5])
    bad = tmp_path / "bad.toml"
    bad.write_text('volume = "1,2"\n')
    with pytest.raises(CliError, match="--volume: flight volume '1,2'"):
        fly_cmd._volume(parse(fly_cmd, ["--connect", "udpout:127.0.0.1:9", "--instruction", "go", "--config", str(bad)]))


@pytest.mark.parametrize(
    "text, match",
    [
        ("[planner]\nv_max_mps = 0.3\n", r"unknown table\(s\) or key\(s\) \['planner'\]"),
        ("[pilot]\nv_max_mps = 0.3\n", r"\[pilot\]: .*v_max_mps"),
        ("[fly]\nvolume = [0, 0, 0, 1, 1, 1]\ngeofence = 1\n", r"unknown key\(s\) in \[fly\] \['geofence'\]"),
        ("pilot = 3\n", r"'pilot' must be a table"),
        ("volume = [0, 0, 0, 1, 1, 1]\n[fly]\nvolume = [0, 0, 0, 2, 2, 2]\n", "both at the top level and in"),
        ("[pilot\n", "not valid TOML"),
    ],
)
def test_fly_config_is_strict_and_names_the_file(tmp_path, capsys, text, match):
    from onfly.cli import main

    cfg = tmp_path / "fly.toml"
    cfg.write_text(text)
    assert main(["fly", "--connect", "udpout:127.0.0.1:9", "--instruction", "go", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cfg) in err[0]
    assert re.search(match, err[0]), err[0]
