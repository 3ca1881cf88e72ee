"""Bad input to run / bench / sweep / replay / tasks: exit status 2, one line naming what is
wrong, no traceback, nothing written; a benchmark with errored episodes exits non-zero and
names them."""

from __future__ import annotations

import socket

import pytest

from onfly.cli import main

CMD_PREFIX = {"run": "onfly run: error: ", "bench": "onfly bench: error: ", "sweep": "onfly sweep: error: ",
              "replay": "onfly replay: error: ", "tasks": "onfly tasks: error: "}

BENCH = """[bench]
name = "b"
methods = ["oracle"]
runs = 1
vlm = "sim:nominal"
[bench.tasks]
ids = ["parking_lot-o01"]
[episode]
time_limit_s = 1.0
[world]
width_px = 64
height_px = 43
"""


@pytest.fixture
def cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def one_line_error(capsys, argv: list[str], match: str, written_before: set | None = None, folder=None) -> str:
    rc = main(argv)
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2, (rc, out, err)
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith(CMD_PREFIX[argv[0]]), lines[0]
    assert match in lines[0], lines[0]
    if folder is not None:
        now = {p.relative_to(folder) for p in folder.rglob("*")}
        assert now == (written_before or set()), f"wrote {sorted(map(str, now - (written_before or set())))}"
    return lines[0]


def _files(folder, **texts) -> set:
    for name, text in texts.items():
        (folder / name.replace("__", ".")).write_text(text)
    return {p.relative_to(folder) for p in folder.rglob("*")}


# -- onfly run ------------------------------------------------------------------------------------


def test_run_bad_backend_task_method(cwd, capsys):
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--vlm", "sim:nomnal"],
                   "--vlm: bad VLM backend spec 'sim:nomnal': unknown simulated-VLM preset 'nomnal'", set(), cwd)
    port = _closed_port()
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--vlm", f"http://127.0.0.1:{port}#qwen"],
                   f"--vlm: VLM backend 'http://127.0.0.1:{port}#qwen' cannot be reached", set(), cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o99"], "--task: no task 'parking_lot-o99'", set(), cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--method", "onfli"], "--method must be one of", set(), cwd)
    one_line_error(capsys, ["run", "--scene", "villa", "--instruction", "fly to the pool"], "--instruction needs --scene and --goal-object", set(), cwd)
    one_line_error(capsys, ["run", "--scene", "villla", "--instruction", "x", "--goal-object", "pool edge"], "--scene: no scene named 'villla'", set(), cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--files", "missing.toml"], "--files: task file not found: missing.toml", set(), cwd)


def test_run_strict_config(cwd, capsys):
    before = _files(cwd, a__toml="[planner]\nv_max_mps = 0.3\nbogus = 1\n", b__toml="[plannr]\nv_max_mps = 0.3\n",
                    c__toml="[planner\n", d__toml="[world]\nwidth = 3\n", e__toml="[pilot]\nverify = false\n")
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--config", "a.toml"], "a.toml: options of method 'onfly': unknown planner option(s) ['bogus']", before, cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--config", "b.toml"], "b.toml: unknown table(s) or key(s) ['plannr']", before, cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--config", "c.toml"], "c.toml: not valid TOML", before, cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--config", "d.toml"], "d.toml: [world]: unknown key(s) ['width']", before, cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--config", "e.toml", "--method", "oracle"],
                   "e.toml: [pilot] holds PilotConfig fields; method 'oracle' is not an OnFly variant", before, cwd)
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--config", "nope.toml"], "nope.toml: run config file not found", before, cwd)


def test_run_planner_table_without_pilot_reaches_the_planner():
    """[planner] alone (no [pilot]) is read: it used to fly exactly like no config."""
    from pathlib import Path
    import tempfile

    from onfly.bench.onfly_method import make_onfly_factory
    from onfly.commands.run import read_run_config

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.toml"
        p.write_text("[planner]\nv_max_mps = 0.3\n[pilot]\nmonitor_period_s = 3.0\n[episode]\nframe_period_s = 1.0\n")
        with pytest.raises(ValueError, match=r"\[planner\] and \[pilot.planner\] both given"):
            p2 = Path(d) / "c2.toml"
            p2.write_text("[planner]\nv_max_mps = 0.3\n[pilot.planner]\nw_yaw = 1.0\n")
            read_run_config(p2, "onfly")
        options, episode, world = read_run_config(p, "onfly")
    method = make_onfly_factory("onfly")("sim:nominal", 0, **options)
    assert method.config.planner.v_max_mps == 0.3 and method.config.monitor_period_s == 3.0
    assert episode == {"frame_period_s": 1.0} and world == {}


def test_run_never_overwrites_a_recording(cwd, capsys):
    (cwd / "old.rrd").write_text("keep")
    one_line_error(capsys, ["run", "--task", "parking_lot-o01", "--method", "oracle", "--rrd", "old.rrd"],
                   "--rrd old.rrd exists; pass --overwrite", {__import__("pathlib").Path("old.rrd")}, cwd)
    assert (cwd / "old.rrd").read_text() == "keep"


def test_recording_names_carry_task_method_backend_seed_and_never_collide(tmp_path):
    from onfly.commands.run import backend_slug, recording_path

    assert backend_slug("sim:nominal") == "sim-nominal"
    assert backend_slug("http://127.0.0.1:8000#Qwen/Qwen2.5-VL-3B") == "Qwen-Qwen2.5-VL-3B"
    p = recording_path("villa-o01", "onfly", "sim:noisy", 3, tmp_path)
    assert p == tmp_path / "villa-o01-onfly-sim-noisy-s3.rrd"
    p.write_text("x")
    assert recording_path("villa-o01", "onfly", "sim:noisy", 3, tmp_path) == tmp_path / "villa-o01-onfly-sim-noisy-s3-2.rrd"
    assert recording_path("villa-o01", "oracle", "sim:noisy", 3, tmp_path) == tmp_path / "villa-o01-oracle-sim-noisy-s3.rrd"


# -- onfly bench ----------------------------------------------------------------------------------


def test_bench_checks_everything_before_the_first_episode(cwd, capsys):
    before = _files(cwd, b__toml=BENCH, k__toml=BENCH + "[planner]\nbogus = 1\n", u__toml=BENCH.replace("runs = 1", "runs = 1\nrun = 2"))
    one_line_error(capsys, ["bench", "--config", "b.toml", "--vlm", "sim:nomnal"], "b.toml: bench.vlm: bad VLM backend spec 'sim:nomnal'", before, cwd)
    port = _closed_port()
    one_line_error(capsys, ["bench", "--config", "b.toml", "--vlm", f"http://127.0.0.1:{port}#m"], "cannot be reached", before, cwd)
    one_line_error(capsys, ["bench", "--config", "b.toml", "--methods", "oracle,onfli"], "unknown method(s) ['onfli']", before, cwd)
    one_line_error(capsys, ["bench", "--config", "b.toml", "--tasks", "villa-o99"], "task selection: unknown task id(s) ['villa-o99']", before, cwd)
    one_line_error(capsys, ["bench", "--config", "b.toml", "--scene", "vila"], "task selection: no tasks for scene(s) ['vila']", before, cwd)
    one_line_error(capsys, ["bench", "--config", "k.toml"], "k.toml: options of method 'oracle' (tables/keys ['planner']): unknown planner config field(s) ['bogus']", before, cwd)
    one_line_error(capsys, ["bench", "--config", "u.toml"], "u.toml: [bench]: unknown field(s) ['run']", before, cwd)
    _files(cwd, mm__toml=BENCH + "[methods.onfli]\nverify = false\n")
    before = before | {__import__("pathlib").Path("mm.toml")}
    one_line_error(capsys, ["bench", "--config", "mm.toml"], "mm.toml: [methods.onfli]: no registered method 'onfli'", before, cwd)
    one_line_error(capsys, ["bench", "--config", "b.toml", "--count", "0"], "--count must be a positive integer, got 0", before, cwd)
    one_line_error(capsys, ["bench", "--config", "missing.toml"], "benchmark config not found: missing.toml", before, cwd)


class _Broken:
    """A method whose step raises: the benchmark must say so and exit non-zero."""

    privileged = False

    def reset(self, spec) -> None:
        pass

    def step(self, t_s, state, obs):
        raise RuntimeError("deliberate failure in step")

    def summary(self) -> dict:
        return {}


def test_bench_with_errored_episodes_exits_non_zero_and_names_them(cwd, capsys):
    from onfly.bench import registry

    registry.register("h20_broken", lambda vlm, seed, **opts: _Broken(), replace=True)
    try:
        _files(cwd, b__toml=BENCH)
        rc = main(["bench", "--config", "b.toml", "--methods", "h20_broken", "--no-progress", "--out", "out", "--workers", "1"])
    finally:
        registry.METHODS.pop("h20_broken", None)
    out, err = capsys.readouterr()
    assert rc == 1
    assert "1 episode(s) ended with a method error" in err
    assert "h20_broken/parking_lot-o01/run0: RuntimeError: deliberate failure in step" in err
    assert "Traceback" not in err


# -- onfly sweep ----------------------------------------------------------------------------------


def test_sweep_bad_files(cwd, capsys):
    before = _files(
        cwd, base__toml=BENCH,
        t__toml='[sweep]\nbase = "base.toml"\n[grid]\nplanner.w_yaw = [1.0]\n[gird]\nx = 1\n',
        s__toml='[sweep]\nbase = "base.toml"\n[sweep.tasks]\ncont = 3\n[grid]\nplanner.w_yaw = [1.0]\n',
        m__toml='[sweep]\nbase = "nowhere.toml"\n[grid]\nplanner.w_yaw = [1.0]\n',
        q__toml='[sweep]\nbase = "base.toml"\n[search]\ntrials = 2\n[search.space]\nplanner.w_yaw = { low = 2.0, high = 1.0 }\n',
        o__toml='[sweep]\nbase = "base.toml"\n[search]\nobjectives = ["SR:up"]\n[search.space]\nplanner.w_yaw = { low = 1.0, high = 2.0 }\n',
        g__toml='[sweep]\nbase = "base.toml"\n[grid]\nplanner.w_yaw = [1.0]\n',
    )
    one_line_error(capsys, ["sweep", "--config", "t.toml"], "t.toml: unknown table(s) or key(s) ['gird']", before, cwd)
    one_line_error(capsys, ["sweep", "--config", "s.toml"], "s.toml: [sweep.tasks]: unknown key(s) ['cont']", before, cwd)
    one_line_error(capsys, ["sweep", "--config", "m.toml"], "m.toml: [sweep] base 'nowhere.toml' not found", before, cwd)
    one_line_error(capsys, ["sweep", "--config", "q.toml"], "q.toml: [search.space] planner.w_yaw: needs finite numbers low < high", before, cwd)
    one_line_error(capsys, ["sweep", "--config", "o.toml"], "o.toml: [search] objective 'SR:up'", before, cwd)
    one_line_error(capsys, ["sweep", "--config", "g.toml", "--trials", "3"], "--trials and --sampler-seed apply to a [search] config", before, cwd)
    one_line_error(capsys, ["sweep", "--config", "g.toml", "--workers", "0"], "--workers must be a positive integer", before, cwd)


# -- onfly replay / tasks ---------------------------------------------------------------------------


def test_replay_and_tasks_bad_flags(cwd, capsys):
    before = _files(cwd, r__toml="[replay]\nmax_frames = 3\n[planner]\nv_max_mps = 0.3\n", rec__bag="not a bag")
    one_line_error(capsys, ["replay", "rec.bag", "--tf-parent", "odom"], "--tf-parent and --tf-child go together", before, cwd)
    one_line_error(capsys, ["replay", "rec.bag", "--config", "r.toml"], "r.toml: unknown table(s) or key(s) ['planner']; valid tables: ['replay']", before, cwd)
    one_line_error(capsys, ["tasks", "list", "--count", "0"], "--count must be a positive integer, got 0", before, cwd)
    one_line_error(capsys, ["tasks", "list", "--tasks", "villa-o99"], "task selection: unknown task id(s) ['villa-o99']", before, cwd)


def test_reader_field_names_become_flags():
    from onfly.commands.replay import flag_names

    msg = "topic /tf is a TF topic; pass tf_parent_frame and tf_child_frame (BagConfig.pose_topic)"
    assert flag_names(msg) == "topic /tf is a TF topic; pass --tf-parent and --tf-child (--pose-topic)"
