"""The CLI starts without the heavy stack: ``onfly --help``, every command's ``--help`` and
argument errors import none of open3d, torch, casadi, scipy or rosbags (checked in a fresh
interpreter through ``sys.modules``); values with a leading minus sign reach their option."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from onfly.cli import attach_negative_values, command_specs

HEAVY = ("open3d", "torch", "casadi", "scipy", "rosbags", "transformers", "rerun", "cv2")
#: h18's commands (fly, sim-vehicle) keep their own imports light; they are held to it too.
COMMANDS = [s.name for s in command_specs()]

PROBE = r"""
import contextlib, io, json, sys
argv = json.loads(sys.argv[1])
err = io.StringIO()
code = None
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
    import onfly.cli
    try:
        code = onfly.cli.main(argv)
    except SystemExit as exc:
        code = exc.code
heavy = sorted({m.split(".")[0] for m in sys.modules} & set(json.loads(sys.argv[2])))
print(json.dumps({"code": code, "heavy": heavy, "stderr": err.getvalue()}))
"""


def _probe(argv: list[str]) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, json.dumps(argv), json.dumps(HEAVY)],
                         capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_onfly_and_the_cli_help_load_no_heavy_module():
    r = _probe(["--help"])
    assert r["code"] == 0
    assert r["heavy"] == []


def test_every_command_is_listed_without_importing_it():
    names = {s.name for s in command_specs()}
    assert {"run", "bench", "sweep", "replay", "tasks", "render", "scenes", "bag-info", "fly", "sim-vehicle"} <= names
    assert all(s.help for s in command_specs())


@pytest.mark.parametrize("command", ["run", "bench", "sweep", "replay", "tasks", "render", "scenes", "bag-info"])
def test_command_help_and_argument_errors_load_no_heavy_module(command):
    r = _probe([command, "--help"])
    assert r["code"] == 0, r
    assert r["heavy"] == [], f"`onfly {command} --help` imported {r['heavy']}"
    r = _probe([command, "--no-such-flag"])
    assert r["code"] == 2
    assert r["heavy"] == [], f"`onfly {command} --no-such-flag` imported {r['heavy']}"
    assert "unrecognized arguments: --no-such-flag" in r["stderr"] or "required" in r["stderr"]
    assert "Traceback" not in r["stderr"]


def test_value_errors_found_before_the_stack_loads():
    r = _probe(["render", "--scene", "villa", "--pose", "-3,0,6"])
    assert r["code"] == 2 and r["heavy"] == []
    assert r["stderr"].strip() == "onfly render: error: --pose must be four finite numbers x,y,z,yaw, got '-3,0,6'"
    r = _probe(["run", "--task", "villa-o01", "--width", "0"])
    assert r["code"] == 2 and r["heavy"] == []
    assert r["stderr"].strip() == "onfly run: error: --width must be a positive number of pixels, got 0"


def test_flag_value_errors_of_bench_sweep_tasks_load_no_heavy_module():
    for argv, line in (
        (["bench", "--config", "x.toml", "--count", "0"], "onfly bench: error: --count must be a positive integer, got 0"),
        (["sweep", "--config", "x.toml", "--workers", "0"], "onfly sweep: error: --workers must be a positive integer, got 0"),
        (["bench", "--config", "x.toml", "--ray", " "], "onfly bench: error: --ray needs a cluster address or 'local'"),
    ):
        r = _probe(argv)
        assert r["code"] == 2 and r["heavy"] == [], (argv, r)
        assert r["stderr"].strip() == line


def test_unknown_command_is_an_argument_error():
    r = _probe(["rnu"])
    assert r["code"] == 2 and r["heavy"] == []
    assert "invalid choice: 'rnu'" in r["stderr"]


def test_negative_numbers_reach_their_option():
    assert attach_negative_values(["render", "--pose", "-3,0,6,0", "--out", "x"]) == ["render", "--pose=-3,0,6,0", "--out", "x"]
    assert attach_negative_values(["replay", "p", "--goal", "-1.5,-2e-1,3"]) == ["replay", "p", "--goal=-1.5,-2e-1,3"]
    assert attach_negative_values(["run", "--seed", "-1"]) == ["run", "--seed=-1"]
    # an option after an option is not a value; words are left alone
    assert attach_negative_values(["bench", "--tasks", "-v"]) == ["bench", "--tasks", "-v"]
    assert attach_negative_values(["x", "--pose", "-3,a"]) == ["x", "--pose", "-3,a"]
