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
import signal
import socket
import subprocess
import sys
import threading
import time

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


def test_in_process_sim_vehicle_and_fly_complete_a_short_task(tmp_path):
    mav, cam = free_port(), free_port(socket.SOCK_STREAM)
    vehicle_json, fly_json = tmp_path / "vehicle.json", tmp_path / "fly.json"
    vehicle_args = parse(sim_vehicle_cmd, [
        "--mavlink", f"udpin:127.0.0.1:{mav}", "--task", TASK, "--start", "2.2", "-21.5", "75",
        "--camera", f"tcp://127.0.0.1:{cam}", "--duration-s", "90", "--json", str(vehicle_json),
    ])
    stop = threading.Event()
    vehicle = threading.Thread(target=sim_vehicle_cmd.run, args=(vehicle_args,), kwargs={"stop": stop}, daemon=True)
    vehicle.start()
    try:
        rc = fly_cmd.run(parse(fly_cmd, [
            "--connect", f"udpout:127.0.0.1:{mav}", "--camera", f"tcp://127.0.0.1:{cam}", "--task", TASK,
            "--vlm", "sim:perfect", "--hold-s", "0.5", "--time-limit-s", "40", "--json", str(fly_json),
        ]))
        time.sleep(1.5)  # PX4's offboard loss timeout (1 s) after the hand-over: the vehicle takes the hover
    finally:
        stop.set()
        vehicle.join(10.0)
    summary = json.loads(fly_json.read_text())
    truth = json.loads(vehicle_json.read_text())
    kinds = [e["kind"] for e in summary["events"]]
    print(f"in-process short {TASK}: end {summary['end_reason']}, flight {summary['flight_time_s']:.1f} s, "
          f"take-off {summary['takeoff_s']:.1f} s, NE {summary['metrics']['navigation_error_m']:.2f} m, loop {summary['loop']}")
    assert rc == 0 and summary["end_reason"] == "finished" and summary["finished"]
    # take-off, offboard, flight, STOP, hold: in this order
    order = ["engaged", "takeoff_done", "begin", "pilot_finished", "hold", "handover_hold"]
    assert [k for k in kinds if k in order] == order
    assert summary["metrics"]["success"] and summary["metrics"]["navigation_error_m"] < 5.0
    assert 1.5 - 0.15 <= summary["trace_t_x_y_z"][0][3] <= 1.5 + 0.15  # took off to the task's start height
    # the vehicle's ground truth: no collision, it is where the companion thinks, it saw the stream
    assert truth["world"]["collision"] is None and truth["world"]["out_of_bounds_s"] is None
    assert np.linalg.norm(np.array(truth["world"]["position_m"]) - np.array(summary["final_position_m"])) < 0.3
    assert goal_distance(truth["world"]["position_m"]) < 5.0
    assert truth["frames_served"] > 5 and summary["camera"]["received"] > 5
    modes = [e["text"] for e in truth["vehicle_events"] if e["text"].startswith("mode")]
    assert modes[0].startswith("mode offboard") and modes[-1].startswith("mode auto.loiter: offboard lost")
    # no failsafe during the mission itself; the hand-over's offboard loss is marked as such
    assert all(f["after_handover"] for f in summary["failsafes"] if not f["cleared"])


def _run_benchmark_reference(tmp_path, seed):
    out = tmp_path / "run.json"
    subprocess.run(
        [sys.executable, "-c", "import sys; from onfly.cli import main; sys.exit(main(sys.argv[1:]))",
         "run", "--task", TASK, "--vlm", "sim:perfect", "--seed", str(seed), "--no-rrd", "--json", str(out)],
        check=True, capture_output=True, timeout=300,
    )
    return json.loads(out.read_text())


@pytest.mark.slow
def test_two_processes_fly_a_benchmark_task_with_the_benchmark_success(tmp_path):
    seed = 0
    mav, cam = free_port(), free_port(socket.SOCK_STREAM)
    vehicle_json, fly_json = tmp_path / "vehicle.json", tmp_path / "fly.json"
    entry = [sys.executable, "-c", "import sys; from onfly.cli import main; sys.exit(main(sys.argv[1:]))"]
    vehicle = subprocess.Popen(
        entry + ["sim-vehicle", "--mavlink", f"udpin:127.0.0.1:{mav}", "--task", TASK, "--camera", f"tcp://127.0.0.1:{cam}",
                 "--duration-s", "150", "--json", str(vehicle_json)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        t0 = time.monotonic()
        fly = subprocess.run(
            entry + ["fly", "--connect", f"udpout:127.0.0.1:{mav}", "--camera", f"tcp://127.0.0.1:{cam}", "--task", TASK,
                     "--vlm", "sim:perfect", "--seed", str(seed), "--json", str(fly_json)],
            capture_output=True, text=True, timeout=240,
        )
        wall_s = time.monotonic() - t0
    finally:
        vehicle.send_signal(signal.SIGINT)  # the vehicle writes its ground truth on Ctrl-C
        vehicle_out, _ = vehicle.communicate(timeout=20)
    assert fly.returncode == 0, fly.stderr[-3000:]
    summary = json.loads(fly_json.read_text())
    truth = json.loads(vehicle_json.read_text())
    reference = _run_benchmark_reference(tmp_path, seed)
    m, ref = summary["metrics"], reference["metrics"]
    print(f"\n{TASK} seed {seed}: two processes success {m['success']} flight {m['flight_time_s']:.1f} s NE {m['navigation_error_m']:.2f} m "
          f"(take-off {summary['takeoff_s']:.1f} s, wall {wall_s:.1f} s); onfly run success {ref['success']} flight "
          f"{ref['flight_time_s']:.1f} s NE {ref['navigation_error_m']:.2f} m")
    assert m["success"] == ref["success"] is True
    assert abs(m["flight_time_s"] - ref["flight_time_s"]) < 5.0
    assert truth["world"]["collision"] is None, truth["world"]
    assert goal_distance(truth["world"]["position_m"]) < 5.0
    assert "mode offboard" in vehicle_out


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
