"""experiments/tables_of_record.py and experiments/print_tables.py: one command flies every
table's episodes once (shared where the runner's keys coincide), resumes, refuses a folder of
other code, and the tables print again from the records file alone."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest

from experiments import print_tables as pt
from experiments import tables_of_record as tor
from experiments.paper_tables import PAPER
from onfly.bench.runner import EPISODES_FILE, BenchConfig, plan_jobs, read_records, summarize_records
from onfly.bench.tasks import load_tasks, select_tasks

REPO = Path(__file__).resolve().parents[1]
# warehouse-o01 starts with its forklift out of view, urban_block-o02 with its hydrant in view
# (tests/test_task_visibility.py, 160 x 107 px)
TASKS = ["warehouse-o01", "urban_block-o02"]
IN_VIEW = {"warehouse-o01": False, "urban_block-o02": True}
CODE = tor.CodeVersion("00000000feedc0de", "1234abcd-dirty")

BENCH = f"""
[bench]
name = "tiny"
methods = ["oracle"]
runs = 1
vlm = "sim:nominal"
[bench.tasks]
ids = {json.dumps(TASKS)}
[episode]
time_limit_s = 3.0
[world]
width_px = 160
height_px = 107
"""

MANIFEST = """
[record]
name = "tiny_record"
workers = 1
[labels]
oracle = "Oracle"
spf = "SPF"
[paper]
"SPF" = [26.4, 61.5, 42.7, 39.2]

[tables.main]
title = "Main table"
config = "tiny.toml"
methods = ["oracle", "spf"]
runs = 2
paper = true

[tables.again]
title = "SPF again"
config = "tiny.toml"
methods = ["spf"]
runs = 1

[tables.split]
title = "Ideal against realistic"
methods = ["oracle"]
runs = 1
split_view = true
[[tables.split.parts]]
label = "ideal"
config = "tiny.toml"
[[tables.split.parts]]
label = "realistic"
config = "tiny.toml"
realism = "realistic"
"""


def write_manifest(folder: Path, text: str = MANIFEST) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "tiny.toml").write_text(BENCH)
    (folder / "m.toml").write_text(text)
    return folder / "m.toml"


def run_main(args: list[str], code: tor.CodeVersion = CODE) -> tuple[int, str, str]:
    """``tables_of_record.main`` with a fixed code version; returns (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        mp.setattr(tor, "code_version", lambda *a, **k: code)
        rc = tor.main(args)
    return rc, out.getvalue(), err.getvalue()


def expected_keys(folder: Path) -> dict[str, tuple[str, str, int, str]]:
    """key -> (method, task, run, realism) of every distinct episode the tiny manifest plans,
    from the runner's own planning."""
    base = BenchConfig.from_toml(folder / "tiny.toml")
    tasks = select_tasks(load_tasks(), ids=TASKS)
    out = {}
    for b, realism in ((replace(base, methods=("oracle", "spf"), runs=2), "ideal"),
                       (replace(base, methods=("oracle",), world={**base.world, "realism": "realistic"}), "realistic")):  # fmt: skip
        for j in plan_jobs(b, tasks):
            out[j.key] = (j.method, j.task_id, j.run_index, realism)
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("record")
    manifest = write_manifest(folder)
    out = folder / "out"
    rc, stdout, stderr = run_main(["--manifest", str(manifest), "--out", str(out), "--json", str(folder / "t.json")])
    assert rc == 0, stderr
    return {"folder": folder, "manifest": manifest, "out": out, "stdout": stdout, "stderr": stderr}


def test_records_hold_every_planned_episode_exactly_once(tiny):
    header, recs = pt.read_records_file(tiny["out"] / tor.RECORDS_FILE)
    expect = expected_keys(tiny["folder"])
    keys = [r["key"] for r in recs]
    assert len(keys) == len(set(keys)) == 10 and set(keys) == set(expect)
    for r in recs:
        method, task, run, realism = expect[r["key"]]
        assert (r["method"], r["task"], r["run"], r["realism"], r["error_model"]) == (method, task, run, realism, "nominal")
        # the tables and sets each episode belongs to: spf run 0 is also "again"'s, oracle run 0
        # also the split table's ideal set; the realistic episodes only the split's second set
        if realism == "realistic":
            want = {"split": [1]}
        elif run == 1:
            want = {"main": [0]}
        else:
            want = {"main": [0], "again": [0]} if method == "spf" else {"main": [0], "split": [0]}
        assert r["tables"] == want, r["key"]
        assert ("start_in_view" in r) == ("split" in want)
        if "split" in want:
            assert r["start_in_view"] is IN_VIEW[task]
        assert set(r) <= set(pt.RECORD_FIELDS) and "method_summary" not in r and "vlm_calls" not in r
    # one shared folder per underlying config: ideal holds 8 episodes, realistic 2, each once
    pools = sorted(p.name for p in (tiny["out"] / "pools").iterdir())
    assert len(pools) == 2 and pools[0].startswith("nominal-ideal-") and pools[1].startswith("nominal-realistic-")
    lines = {p: [r["key"] for r in read_records(tiny["out"] / "pools" / p / EPISODES_FILE)] for p in pools}
    assert sorted(map(len, lines.values())) == [2, 8] and all(len(v) == len(set(v)) for v in lines.values())
    assert [t["name"] for t in header["tables"]] == ["main", "again", "split"]


def test_compact_records_keep_the_runner_metrics(tiny):
    _, recs = pt.read_records_file(tiny["out"] / tor.RECORDS_FILE)
    full = {r["key"]: r for p in (tiny["out"] / "pools").iterdir() for r in read_records(p / EPISODES_FILE)}
    for r in recs:
        f = full[r["key"]]
        assert r["metrics"]["success"] == f["metrics"]["success"] and r["end_reason"] == f["end_reason"]
        assert r["metrics"]["flight_time_s"] == pytest.approx(f["metrics"]["flight_time_s"], abs=1e-4)
        assert r["metrics"]["navigation_error_m"] == pytest.approx(f["metrics"]["navigation_error_m"], abs=1e-4)
    raw = [json.dumps(r, separators=(",", ":")) for r in recs]
    assert max(map(len, raw)) < 700  # per-episode bulk is left in the run folders
    tables = json.loads((tiny["out"] / "tables.json").read_text())
    main = {r["method"]: r for r in tables["tables"][0]["rows"]}
    pool_main = [full[r["key"]] for r in recs if "main" in r["tables"]]
    s = summarize_records(pool_main, error_model="nominal")["methods"]
    for m in ("oracle", "spf"):
        assert main[m]["episodes"] == main[m]["planned"] == 4
        for k in ("SR", "OSR", "CR"):
            assert main[m][k] == pytest.approx(100 * s[m][k])
        assert main[m]["FT"] == pytest.approx(s[m]["FT"], abs=1e-4)
    assert main["spf"]["paper"] == {"SR": 26.4, "OSR": 61.5, "CR": 42.7, "FT": 39.2} and main["oracle"]["paper"] is None


def test_table_headers_name_error_model_realism_commit_and_wall_time(tiny):
    md = (tiny["out"] / "tables.md").read_text()
    split = md[md.index("## Ideal against realistic") :]
    assert "simulated-VLM error model: `nominal` (per set); realism profile: `ideal`, `realistic` (per set)" in split
    assert "commit `1234abcd-dirty`, code digest `00000000feedc0de`" in split
    state = json.loads((tiny["out"] / tor.STATE_FILE).read_text())
    assert state["code_digest"] == CODE.digest and set(state["tables"]) == {"main", "again", "split"}
    assert all(t["wall_s"] > 0 for t in state["tables"].values())
    wall = state["tables"]["main"]["wall_s"]
    assert f"- wall time: {wall:.0f} s running this table" in md
    assert "| ideal | Oracle | 2 |" in split and "| realistic | Oracle | 2 |" in split
    # one task starts in view and one out of view, in each set (the SR values depend on the flights)
    rows = [line for line in split.splitlines() if line.startswith(("| ideal |", "| realistic |"))]
    assert len(rows) == 2 and all(line.count(" (1) | ") == 2 for line in rows)
    assert "**Subset check" not in md and "Mixed code versions" not in md


def test_printed_tables_equal_what_the_command_wrote(tiny):
    gz = str(tiny["out"] / tor.RECORDS_FILE)
    md = (tiny["out"] / "tables.md").read_text()
    assert tiny["stdout"] == md
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert pt.main([gz]) == 0
    assert out.getvalue() == md
    for name in ("main", "again", "split"):
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert pt.main([gz, "--table", name]) == 0
        section = out.getvalue()
        assert section.startswith("## ") and f"(`{name}`)" in section.splitlines()[0] and section in md
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert pt.main([gz, "--format", "json"]) == 0
    assert out.getvalue() == (tiny["out"] / "tables.json").read_text() == (tiny["folder"] / "t.json").read_text()


def test_a_second_run_flies_nothing(tiny, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(tiny["out"], out)
    before = {p.name: (p / EPISODES_FILE).read_text() for p in (out / "pools").iterdir()}

    def no_flight(job):
        raise AssertionError(f"episode flown again: {job.key}")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("onfly.bench.runner.run_job", no_flight)
        rc, _, err = run_main(["--manifest", str(tiny["manifest"]), "--out", str(out)])
    assert rc == 0, err
    assert {p.name: (p / EPISODES_FILE).read_text() for p in (out / "pools").iterdir()} == before
    assert err.count(", 0 to fly") == 4 and "to fly" in err  # 4 sets, every episode recorded
    _, recs = pt.read_records_file(out / tor.RECORDS_FILE)
    _, recs0 = pt.read_records_file(tiny["out"] / tor.RECORDS_FILE)
    assert recs == recs0


def test_from_runs_only_reads(tiny, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(tiny["out"], out)
    for name in (tor.RECORDS_FILE, "tables.md", "tables.json"):
        (out / name).unlink()

    def no_flight(job):
        raise AssertionError(f"episode flown: {job.key}")

    other = tor.CodeVersion("ffffffff00000000", "5678ef01")  # reading needs no code check
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("onfly.bench.runner.run_job", no_flight)
        rc, _, err = run_main(["--manifest", str(tiny["manifest"]), "--out", str(out), "--from-runs"], other)
    assert rc == 0, err
    md, md0 = (out / "tables.md").read_text(), (tiny["out"] / "tables.md").read_text()
    assert md[md.index("\n## ") :] == md0[md0.index("\n## ") :]  # every table as written by the run
    assert pt.read_records_file(out / tor.RECORDS_FILE)[1] == pt.read_records_file(tiny["out"] / tor.RECORDS_FILE)[1]
    rc, _, err = run_main(["--manifest", str(tiny["manifest"]), "--out", str(tmp_path / "none"), "--from-runs"])
    assert rc == 2 and "--from-runs: no output folder" in err


def test_another_code_digest_is_refused_unless_mixed(tiny, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(tiny["out"], out)
    other = tor.CodeVersion("ffffffff00000000", "5678ef01")
    args = ["--manifest", str(tiny["manifest"]), "--out", str(out)]
    rc, _, err = run_main(args, other)
    assert rc == 2
    assert "code digest 00000000feedc0de" in err and "digest ffffffff00000000" in err and "--allow-mixed" in err
    assert json.loads((out / tor.STATE_FILE).read_text())["code_versions"] == [CODE.as_dict()]
    rc, _, err = run_main(args + ["--allow-mixed"], other)
    assert rc == 0, err
    md = (out / "tables.md").read_text()
    assert "Mixed code versions" in md and "code digest `ffffffff00000000`" in md and "**mixed code versions**" in md


def test_a_code_change_during_the_run_stops_it(tiny, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(tiny["out"], out)
    planned = tor.plan_tables(tor.load_manifest(tiny["manifest"]))
    seen = iter([CODE, tor.CodeVersion("0123456789abcdef", CODE.commit)])
    msg = r"changed during the run: digest 00000000feedc0de at the start, 0123456789abcdef now \(before table 'again'\)"
    with pytest.raises(tor.CodeVersionError, match=msg):
        tor.run_tables(planned, out, ["main", "again"], code=CODE, check=lambda: next(seen))


def test_tables_option_runs_only_those_and_the_artifacts_cover_all(tmp_path):
    manifest = write_manifest(tmp_path / "m")
    rc, _, err = run_main(["--manifest", str(manifest), "--out", str(tmp_path / "out"), "--tables", "again", "--no-progress"])
    assert rc == 0, err
    _, recs = pt.read_records_file(tmp_path / "out" / tor.RECORDS_FILE)
    assert sorted((r["method"], r["run"]) for r in recs) == [("spf", 0), ("spf", 0)]
    tables = {t["name"]: t for t in json.loads((tmp_path / "out" / "tables.json").read_text())["tables"]}
    assert [(t["episodes"], t["planned"]) for t in tables.values()] == [(2, 8), (2, 2), (0, 4)]
    assert tables["main"]["wall_s"] is None and tables["again"]["wall_s"] > 0
    assert "[again] 1/2" not in err and "[1/1 again] done" in err  # --no-progress: no line per episode


def test_methods_option_flies_only_those_rows_and_a_later_run_the_rest(tmp_path):
    manifest = write_manifest(tmp_path / "m")
    out = tmp_path / "out"
    rc, _, err = run_main(["--manifest", str(manifest), "--out", str(out), "--tables", "main", "--methods", "spf", "--no-progress"])
    assert rc == 0, err
    _, recs = pt.read_records_file(out / tor.RECORDS_FILE)
    assert sorted((r["method"], r["run"]) for r in recs) == [("spf", 0), ("spf", 0), ("spf", 1), ("spf", 1)]
    assert "incomplete: main has 4 of 8 episodes" in err
    rc, _, err = run_main(["--manifest", str(manifest), "--out", str(out), "--tables", "main", "--no-progress"])
    assert rc == 0, err
    _, recs = pt.read_records_file(out / tor.RECORDS_FILE)
    keys = [r["key"] for r in recs if "main" in r["tables"]]
    assert len(keys) == len(set(keys)) == 8  # the spf episodes were not flown again
    assert {r["key"] for r in recs} <= set(expected_keys(tmp_path / "m"))
    rc, _, err = run_main(["--manifest", str(manifest), "--out", str(tmp_path / "o2"), "--tables", "again", "--methods", "oracle"])
    assert rc == 2 and "--methods: ['oracle'] not a row of the tables run (again); their rows: spf" in err


def test_code_digest_follows_tracked_code_only(tmp_path):
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t"]
    for rel in ("onfly/a.py", "experiments/configs/c.toml", "docs/d.md"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x = 1\n")
    subprocess.run(git + ["init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(git + ["add", "."], cwd=tmp_path, check=True)
    subprocess.run(git + ["commit", "-q", "-m", "c"], cwd=tmp_path, check=True)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True, text=True).stdout.strip()
    v0 = tor.code_version(tmp_path)
    assert v0.commit == head and len(v0.digest) == 16
    (tmp_path / "docs/d.md").write_text("changed\n")  # not code
    (tmp_path / "onfly/new.py").write_text("untracked\n")
    assert tor.code_version(tmp_path) == v0
    (tmp_path / "experiments/configs/c.toml").write_text("x = 2\n")
    v1 = tor.code_version(tmp_path)
    assert v1.digest != v0.digest and v1.commit == head + "-dirty"
    (tmp_path / "experiments/configs/c.toml").write_text("x = 1\n")
    assert tor.code_version(tmp_path) == v0


@pytest.mark.parametrize(
    "body, match",
    [
        ('[tables.t]\nconfig = "tiny.toml"\ncolumns = 3\n', r"tables\.t: unknown field\(s\) \['columns'\]"),
        ('[tables.t]\nconfig = "nope.toml"\n', r"tables\.t\.config: benchmark config not found: .*nope\.toml"),
        ('[tables.t]\nconfig = "tiny.toml"\nrealism = "foggy"\n', r"tables\.t: realism: unknown profile 'foggy'"),
        ('[tables.t]\nmethods = ["oracle"]\n', r"tables\.t: no config"),
        ('[record]\nname = "x"\n', r"lists no \[tables"),
        ('[paper]\n"SPF" = [1, 2]\n[tables.t]\nconfig = "tiny.toml"\n', r"\[paper\]: each row label maps to \[SR %, OSR %, CR %, FT s\]"),
        ("[tables.t\n", r"not valid TOML"),
        ('[tables.t]\nconfig = "tiny.toml"\n[[tables.t.parts]]\nlabel = "a"\n[[tables.t.parts]]\nlabel = "a"\n', r"two sets share a label"),
    ],
)
def test_bad_manifests_name_the_fault(tmp_path, body, match):
    manifest = write_manifest(tmp_path, body)
    with pytest.raises(tor.ManifestError, match=match):
        tor.load_manifest(manifest)
    rc, _, err = run_main(["--manifest", str(manifest), "--out", str(tmp_path / "out")])
    assert rc == 2 and err.strip().splitlines()[-1].startswith("error: ") and not (tmp_path / "out").exists()


def test_unknown_methods_and_tables_are_usage_errors(tmp_path):
    manifest = write_manifest(tmp_path, '[tables.t]\nconfig = "tiny.toml"\nmethods = ["oracle", "nope"]\n')
    with pytest.raises(tor.ManifestError, match=r"tables\.t: .*unknown method\(s\) \['nope'\]; registered methods: .*oracle"):
        tor.plan_tables(tor.load_manifest(manifest))
    manifest = write_manifest(tmp_path)
    rc, _, err = run_main(["--manifest", str(manifest), "--out", str(tmp_path / "out"), "--tables", "main,tabel2"])
    assert rc == 2 and "unknown table(s) ['tabel2']; the manifest's tables: main, again, split" in err
    assert not (tmp_path / "out").exists()


def test_printer_refuses_what_is_not_a_records_file(tmp_path, capsys):
    (tmp_path / "x.gz").write_text("not gzip")
    assert pt.main([str(tmp_path / "x.gz")]) == 2
    assert "not a gzip file of JSON lines" in capsys.readouterr().err
    header = {"format": pt.FORMAT, "name": "n", "manifest": "m", "code": {"digest": "d", "commit": "c"}, "mixed": False,
              "subset": {"count": 2}, "command": "cmd", "tables": []}  # fmt: skip
    tor.write_artifacts(tmp_path, header, [])
    assert pt.main([str(tmp_path / tor.RECORDS_FILE), "--table", "nope"]) == 2
    assert "no table 'nope'" in capsys.readouterr().err
    assert "**Subset check (count 2): not a table of record.**" in (tmp_path / "tables.md").read_text()


def _rec(task, method, success, end, *, part=0, view=None, track=None, collided=False, clearance=None):
    r = {"key": f"h/{method}/{task}", "tables": {"t": [part]}, "method": method, "task": task, "run": 0, "end_reason": end,
         "failure": "" if success else end, "cpu_s": 1.0,
         "metrics": {"success": success, "oracle_success": success or end == "time_limit", "collided": collided,
                     "flight_time_s": 10.0 if success else 30.0, "navigation_error_m": 1.0, "path_length_m": 5.0,
                     "spl": 0.5 if success else 0.0}}  # fmt: skip
    if view is not None:
        r["start_in_view"] = view
    if clearance is not None:
        r["min_clearance_m"] = clearance
    if track is not None:
        r["track"] = track
    return r


def _header(**flags):
    part = {"label": "a", "config": "c.toml", "pool": "p", "methods": ["m"], "vlm": "sim:weak", "error_model": "weak",
            "realism": "ideal", "runs": 1, "tasks": 3, "paper_row": None}  # fmt: skip
    table = {"name": "t", "title": "T", "note": "", "paper": False, "split_view": False, "track": False, "labels": {"m": "Em"},
             "paper_numbers": {}, "wall_s": 5.0, "code": [{"digest": "d", "commit": "c"}], "parts": [part, {**part, "label": "b"}]}  # fmt: skip
    table.update(flags)
    return {"format": pt.FORMAT, "name": "n", "manifest": "m", "code": {"digest": "d", "commit": "c"}, "mixed": False,
            "subset": None, "command": "cmd", "tables": [table]}  # fmt: skip


def test_rows_split_by_view_and_track_metrics_from_records_alone():
    t1 = {"in_band_frac": 0.8, "band_error_m": 0.2, "times_lost": 1, "times_refound": 1, "stop_ok": True}
    t2 = {"in_band_frac": 0.6, "band_error_m": 0.4, "times_lost": 2, "times_refound": 0, "stop_ok": None}
    recs = [
        _rec("x", "m", False, "collision", view=False, track=t2, collided=True, clearance=0.21),
        _rec("y", "m", True, "stopped", view=True, track=t1, clearance=0.6),
        _rec("z", "m", True, "stopped", view=False),  # no clearance recorded: left out of the minimum
        _rec("w", "m", False, "time_limit", part=1, view=True),
    ]
    table = pt.build_tables(_header(split_view=True, track=True), recs)["tables"][0]
    a, b = table["rows"]
    assert (a["set"], a["label"], a["episodes"], a["planned"]) == ("a", "Em", 3, 3)
    assert a["SR"] == pytest.approx(200 / 3) and a["CR"] == pytest.approx(100 / 3) and a["FT"] == pytest.approx(50 / 3)
    assert a["end_reasons"] == {"stopped": 2, "collision": 1}  # in END_REASONS order, not record order
    assert a["view"] == {"in_view_episodes": 1, "SR_in_view": 100.0, "out_of_view_episodes": 2, "SR_out_of_view": 50.0}
    assert a["track"] == {"episodes": 2, "in_band_pct": pytest.approx(70.0), "band_error_m": pytest.approx(0.3), "lost": 1.5,
                          "refound": 0.5, "stop_held_pct": 100.0}  # fmt: skip
    assert b["episodes"] == 1 and b["SR"] == 0.0 and b["OSR"] == 100.0 and b["track"]["in_band_pct"] is None
    md = pt.format_table(table)
    assert a["min_clearance_m"] == 0.21 and b["min_clearance_m"] is None
    assert "| a | Em | 3 | 66.7 | 66.7 | 33.3 | 16.7 | 1.00 | 0.33 | 0.21 | 100.0 (1) | 50.0 (2) | 70.0 | 0.30 | 1.50 | 0.50 | 100.0 | stopped 2, collision 1 |" in md
    assert "| b | Em | 1 of 3 | 0.0 | 100.0 | 0.0 | 30.0 | 1.00 | 0.00 | n/a | 0.0 (1) | n/a (0) | n/a | n/a | n/a | n/a | n/a | time_limit 1 |" in md
    assert "error model: `weak` (per set)" in md and "- wall time: 5 s running this table" in md and "episodes: 4 of 6" in md


def test_the_manifest_of_record_plans_every_table_and_shares_only_equal_keys():
    m = tor.load_manifest(REPO / "experiments" / "configs" / "tables_of_record.toml")
    assert [t.name for t in m.tables] == ["table2", "planner_study", "table3_architecture", "table3_memory", "table3_backbone",
                                          "search_ablation", "robustness", "tracking", "hard_vs_150"]  # fmt: skip
    assert {k: tuple(v) for k, v in m.paper_numbers.items()} == {k: tuple(float(x) for x in v) for k, v in PAPER.items()}
    planned = tor.plan_tables(m, tor.Subset(count=3))
    by = {(p.table, p.spec.label): p for p in planned}
    ideal, real = by[("robustness", "ideal")], by[("robustness", "realistic")]
    assert ideal.pool == by[("table2", "")].pool and real.pool != ideal.pool and real.pool.startswith("nominal-realistic-")
    paper_keys = {k for p in planned if p.table.startswith(("table", "planner", "search")) for k in p.keys}
    assert set(ideal.keys) <= paper_keys  # every ideal robustness episode is a paper-table / search-ablation run-0 episode
    assert not set(real.keys) & {k for p in planned if p is not real for k in p.keys}
    weak = by[("table3_backbone", "Qwen3-VL-2B (stand-in: sim weak)")]
    assert weak.bench.vlm == "sim:weak" and not set(weak.keys) & set(by[("table2", "")].keys)
    assert all(p.bench.runs == 3 for p in planned if p.table.startswith(("table", "planner", "search")))
    assert by[("tracking", "")].tasks[0].kind == "track" and len(by[("search_ablation", "hard 69")].tasks) == 3


def test_time_left_counts_each_method_at_its_own_mean_and_unseen_ones_at_the_slowest():
    assert tor.estimate_left_s({"spf": 3}, {}, 2) is None  # nothing finished yet: no estimate
    # 4 SPF at 5 s, 2 OnFly at 60 s, 1 w/o search not yet seen (counted at the slowest, 60 s), 2 workers
    left = tor.estimate_left_s({"spf": 4, "onfly": 2, "onfly_no_search": 1}, {"spf": 5.0, "onfly": 60.0}, 2)
    assert left == pytest.approx((4 * 5.0 + 2 * 60.0 + 60.0) / 2)
    assert tor.estimate_left_s({"spf": 0}, {"spf": 5.0}, 1) == 0.0


def test_the_running_tables_wall_time_is_written_while_it_runs(tmp_path):
    """A run killed without unwinding (a machine's reset) keeps the wall time it had written at its
    last checkpoint: with the period at 0 every finished episode writes run_state.json."""
    manifest = write_manifest(tmp_path / "m")
    out = tmp_path / "out"
    seen: list[float] = []
    write = tor._write_state

    def spy(folder, state):
        entry = state["tables"].get("again")
        if entry is not None:
            seen.append(entry["wall_s"])
        write(folder, state)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tor, "CHECKPOINT_S", 0.0)
        mp.setattr(tor, "_write_state", spy)
        rc, _, err = run_main(["--manifest", str(manifest), "--out", str(out), "--tables", "again"])
    assert rc == 0, err
    # one write per finished episode (2) and the table's last one; the account only grows
    assert len(seen) == 3 and seen[0] > 0 and seen == sorted(seen)
    assert json.loads((out / tor.STATE_FILE).read_text())["tables"]["again"]["wall_s"] == pytest.approx(seen[-1])
    assert "(left " in err


def test_a_terminated_run_keeps_its_episodes_and_its_wall_time(tmp_path):
    manifest = write_manifest(tmp_path / "m")
    out = tmp_path / "out"
    script = REPO / "experiments" / "tables_of_record.py"
    cmd = [sys.executable, str(script), "--manifest", str(manifest), "--out", str(out), "--tables", "main"]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120.0
        first = None
        while time.monotonic() < deadline and proc.poll() is None:
            pools = list((out / "pools").glob(f"*/{EPISODES_FILE}")) if (out / "pools").is_dir() else []
            if pools and pools[0].read_text().count("\n") >= 1:
                first = pools[0]
                break
            time.sleep(0.05)
        assert first is not None and proc.poll() is None, "no episode finished before the run ended"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    done = len(read_records(first))
    assert 1 <= done < 8  # the main table plans 8 episodes
    state = json.loads((out / tor.STATE_FILE).read_text())
    assert state["tables"]["main"]["wall_s"] > 0
    # every line on disk is a whole record (test_a_second_run_flies_nothing: a resume skips them)
    lines = first.read_text().splitlines()
    assert len(lines) == done and all(json.loads(line)["key"] for line in lines)


def test_two_worlds_side_by_side_count_what_each_task_lost_and_gained():
    recs = [
        _rec("x", "m", True, "stopped"), _rec("x", "m", False, "collision", part=1, collided=True),  # lost to a collision
        _rec("y", "m", True, "stopped"), _rec("y", "m", False, "time_limit", part=1),  # lost to the time limit
        _rec("z", "m", False, "time_limit"), _rec("z", "m", True, "stopped", part=1),  # gained
        _rec("w", "m", True, "stopped"),  # only in the first world: not a pair
    ]
    header = _header()
    header["tables"][0]["parts"][1]["realism"] = "realistic"
    table = pt.build_tables(header, recs)["tables"][0]
    (row,) = table["paired"]
    assert row["pairs"] == 3 and row["sets"] == ["a", "b"]
    assert row["SR"] == [pytest.approx(200 / 3), pytest.approx(100 / 3)] and row["CR"] == [0.0, pytest.approx(100 / 3)]
    assert (row["lost"], row["lost_end_reasons"], row["gained"]) == (2, {"collision": 1, "time_limit": 1}, 1)
    md = pt.format_table(table)
    assert "| Em | 3 | 66.7 | 33.3 | 0.0 | 33.3 | 2 | collision 1, time_limit 1 | 1 |" in md
    # sets in one world (the _header default) or of other methods are not paired
    assert pt.build_tables(_header(), recs)["tables"][0]["paired"] is None
    other = _header()
    other["tables"][0]["parts"][1].update(realism="realistic", methods=["m", "n"])
    assert pt.build_tables(other, recs)["tables"][0]["paired"] is None


def test_a_method_not_yet_flown_in_a_set_is_estimated_from_its_episodes_in_the_others(tmp_path):
    for pool, recs in (("p1", [("a", 2.0), ("b", 8.0)]), ("p2", [("b", 12.0), ("c", None)])):
        (tmp_path / tor.POOLS_DIR / pool).mkdir(parents=True)
        lines = [json.dumps({"key": f"{pool}/{m}/{i}", "method": m, "wall_s": w}) for i, (m, w) in enumerate(recs)]
        (tmp_path / tor.POOLS_DIR / pool / EPISODES_FILE).write_text("\n".join(lines) + "\n")
    assert tor.recorded_means(tmp_path) == {"a": 2.0, "b": 10.0}  # a record without a wall time counts for nothing
    lines: list[str] = []
    on_episode = tor._episode_reporter("t", set(), lines.append, {"a": 2, "b": 3}, 1, prior_means={"b": 10.0})
    rec = {"key": "k", "method": "a", "task": "x", "run": 0, "end_reason": "stopped", "failure": "", "wall_s": 4.0,
           "metrics": {"success": True}}  # fmt: skip
    on_episode(rec, 1, 5)
    assert lines == ["[t] 1/5 a x run 0: stopped, success (left 34 s)"]  # 1 x 4 s (this set's a) + 3 x 10 s (b's prior)


def test_failed_episodes_list_each_rows_failures_by_kind_with_task_and_run(tmp_path, capsys):
    recs = [
        _rec("x", "m", False, "collision", collided=True),
        _rec("y", "m", True, "stopped"),
        _rec("z", "m", False, "time_limit"),
        _rec("w", "m", False, "time_limit", part=1),
        {**_rec("v", "m", False, "stopped"), "failure": "stopped_outside_radius", "run": 2},
    ]
    header = _header()
    rows = pt.failed_episodes(header, recs, "t")
    assert [(r["set"], r["episodes"]) for r in rows] == [("a", 4), ("b", 1)]
    # END_REASONS order first (collision before time_limit), other kinds after by name
    assert rows[0]["failed"] == {"collision": ["x/0"], "time_limit": ["z/0"], "stopped_outside_radius": ["v/2"]}
    assert rows[1]["failed"] == {"time_limit": ["w/0"]}
    assert pt.failed_episodes(header, recs, "t", method="other") == []
    with pytest.raises(KeyError, match="no table 'nope'"):
        pt.failed_episodes(header, recs, "nope")
    tor.write_artifacts(tmp_path, header, recs)
    path = str(tmp_path / tor.RECORDS_FILE)
    assert pt.main([path, "--failures", "--table", "t"]) == 0
    md = capsys.readouterr().out
    assert "- a: Em: 3 of 4 failed\n  - collision 1: x/0\n  - time_limit 1: z/0\n  - stopped_outside_radius 1: v/2\n" in md
    assert "- b: Em: 1 of 1 failed\n  - time_limit 1: w/0\n" in md
    assert pt.main([path, "--failures", "--table", "t", "--method", "other"]) == 2
    assert "no row of 'other'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        pt.main([path, "--method", "m"])  # --method without --failures is a usage error
    assert "--method needs --failures" in capsys.readouterr().err


def _embedded_doc(name: str, body: str) -> str:
    return f"# Results\n\nBefore.\n\n{pt.EMBED_BEGIN.format(name=name)}\n{body}{pt.EMBED_END}\n\nAfter, kept.\n"


def test_embedded_tables_are_filled_from_the_records_and_checked(tmp_path, capsys):
    recs = [_rec("x", "m", True, "stopped"), _rec("y", "m", False, "time_limit", part=1)]
    header = _header()
    tor.write_artifacts(tmp_path, header, recs)
    tables = pt.build_tables(header, recs)
    readme = tmp_path / "README.md"
    readme.write_text(_embedded_doc("t", "stale table\n"))
    records = str(tmp_path / tor.RECORDS_FILE)
    assert pt.main([records, "--embedded", str(readme)]) == 1  # differs: a diff on stdout
    out = capsys.readouterr()
    assert "-stale table" in out.out and "differ from the records" in out.err
    assert pt.main([records, "--embedded", str(readme), "--write"]) == 0
    text = readme.read_text()
    assert text == _embedded_doc("t", pt.format_table(tables["tables"][0], pt.EMBED_LEVEL))
    assert "#### T (`t`)" in text and "| a | Em | 1 of 3 | 100.0 |" in text and text.endswith("After, kept.\n")
    capsys.readouterr()
    assert pt.main([records, "--embedded", str(readme)]) == 0
    assert "1 embedded tables equal the records (t)" in capsys.readouterr().out
    # one changed figure in the copy is caught
    readme.write_text(text.replace("| 100.0 |", "| 99.0 |", 1))
    assert pt.main([records, "--embedded", str(readme)]) == 1


@pytest.mark.parametrize(
    "doc, match",
    [
        (_embedded_doc("nope", ""), "no table 'nope' in the records"),
        (f"{pt.EMBED_BEGIN.format(name='t')}\nrow\n", "table 't' is never closed"),
        (f"text\n{pt.EMBED_END}\n", "line 2: an end marker with no table open"),
        (f"{pt.EMBED_BEGIN.format(name='t')}\n{pt.EMBED_BEGIN.format(name='t')}\n{pt.EMBED_END}\n", "begins inside table 't'"),
        ("# no tables here\n", "embeds no table of record"),
    ],
)
def test_embedded_markers_that_do_not_pair_are_errors(tmp_path, capsys, doc, match):
    recs = [_rec("x", "m", True, "stopped")]
    tor.write_artifacts(tmp_path, _header(), recs)
    readme = tmp_path / "README.md"
    readme.write_text(doc)
    assert pt.main([str(tmp_path / tor.RECORDS_FILE), "--embedded", str(readme), "--write"]) == 2
    assert match in capsys.readouterr().err
    assert readme.read_text() == doc  # nothing written
