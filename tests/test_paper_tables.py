"""experiments/paper_tables.py: the three tables from finished runs, beside the paper's numbers."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments.paper_tables import (
    PAPER,
    PaperTablesError,
    build_tables,
    check_methods,
    format_markdown,
    load_config,
    main,
    read_runs,
    run_all,
    task_chunks,
)
from onfly.bench.runner import EPISODES_FILE, plan_jobs
from onfly.bench.tasks import load_tasks, select_tasks

TASKS = ["park-o01", "villa-o01"]


def write_config(tmp_path: Path, extra: str = "", backbones: str | None = None) -> Path:
    bb = backbones if backbones is not None else '[["sim:weak", "Qwen3-VL-2B"], ["sim:nominal", "Qwen3-VL-4B"], ["sim:strong", "Qwen3-VL-30B-A3B"]]'
    path = tmp_path / "pt.toml"
    path.write_text(
        f"""
[bench]
name = "pt"
runs = 2
vlm = "sim:nominal"
[bench.tasks]
ids = {json.dumps(TASKS)}
[paper_tables]
backbones = {bb}
[episode]
time_limit_s = 70.0
frame_period_s = 0.5
[world]
width_px = 160
height_px = 107
{extra}
"""
    )
    return path


def fake_records(cfg, vlm: str, outcome) -> list[dict]:
    """Finished-episode records for every job of one VLM spec; ``outcome(method, task, run)``
    gives (success, oracle_success, collided, flight_time_s, end_reason, failure)."""
    bench = cfg.bench_for(vlm)
    tasks = select_tasks(load_tasks(None), ids=bench.task_ids)
    out = []
    for j in plan_jobs(bench, tasks):
        s, o, c, ft, end, fail = outcome(j.method, j.task_id, j.run_index)
        out.append(
            {
                "key": j.key, "method": j.method, "task": j.task_id, "kind": "object", "run": j.run_index, "seed": j.seed,
                "metrics": {"success": s, "oracle_success": o, "collided": c, "flight_time_s": ft, "navigation_error_m": 1.0,
                            "path_length_m": 5.0, "spl": 0.5 if s else 0.0},
                "end_reason": end, "failure": fail, "sim_s": ft, "wall_s": 1.0, "vlm_calls": {}, "vlm_charged_s": {},
                "method_summary": {"calls": 10, "skills": {"find:found": 2}, "uses_map": False}, "min_clearance_m": 0.5,
            }
        )  # fmt: skip
    return out


def outcome(method, task, run):
    if method == "onfly":
        return (True, True, False, 20.0, "stopped", "")
    if method == "typefly" and run == 0:
        return (False, True, True, 10.0, "collision", "collision")
    if method.startswith("onfly_"):
        return (task == "park-o01", True, False, 30.0, "stopped", "" if task == "park-o01" else "stopped_outside_radius")
    return (False, False, False, 70.0, "time_limit", "time_limit")


def write_runs(cfg, root: Path) -> None:
    for vlm, _ in cfg.backbones:
        d = root / vlm.split(":")[1]
        d.mkdir(parents=True)
        with (d / EPISODES_FILE).open("w") as f:
            for r in fake_records(cfg, vlm, outcome):
                f.write(json.dumps(r) + "\n")
            f.write('{"key": "other-config/onfly/park-o01/0", "method": "onfly"}\n')  # not this config: ignored


def test_tables_from_finished_runs(tmp_path):
    cfg = load_config(write_config(tmp_path))
    write_runs(cfg, tmp_path / "runs")
    records = read_runs(cfg, tmp_path / "runs")
    assert len(records["sim:nominal"]) == 10 * 2 * 2 and len(records["sim:weak"]) == 4
    t = build_tables(cfg, records)
    rows = {r["label"]: r for r in t["table2"]}
    assert [r["label"] for r in t["table2"]] == ["TypeFly", "PIVOT", "SPF", "OnFly (ours)"]
    assert (rows["OnFly (ours)"]["SR"], rows["OnFly (ours)"]["CR"], rows["OnFly (ours)"]["FT"]) == (100.0, 0.0, 20.0)
    assert (rows["TypeFly"]["SR"], rows["TypeFly"]["OSR"], rows["TypeFly"]["CR"], rows["TypeFly"]["FT"]) == (0.0, 50.0, 50.0, 40.0)
    assert rows["PIVOT"]["paper"] == {"SR": 10.3, "OSR": 44.2, "CR": 64.1, "FT": 32.9}
    assert [r["label"] for r in t["planner_study"]] == ["SPF w/ planner", "OnFly (ours)"]
    arch = {r["label"]: r for r in t["ablation"]["architecture"]}
    assert arch["w/o Planner"]["SR"] == 50.0 and arch["w/o Planner"]["episodes"] == 4
    assert [r["label"] for r in t["ablation"]["memory"]] == ["Time Sampling", "Sliding Windows", "Hybrid Memory"]
    bb = t["ablation"]["backbone"]
    assert bb[0]["label"] == "Qwen3-VL-2B (stand-in: sim weak)" and bb[0]["error_model"] == "weak" and bb[0]["SR"] == 100.0
    assert bb[0]["paper"]["SR"] == PAPER["Qwen3-VL-2B"][0]
    f = t["failures"]["typefly"]
    assert f["end_reasons"] == {"collision": 2, "time_limit": 2} and f["outcomes"] == {"collision": 2, "time_limit": 2}
    assert f["summary_means"] == {"calls": 10.0, "skills.find:found": 2.0}
    md = format_markdown(t, wall_s={"sim:nominal": 12.0}, command="experiments/paper_tables.py --config x")
    assert "| TypeFly | 4 | 0.0 | 50.0 | 50.0 | 40.0 | 5.7 | 17.5 | 66.5 | 35.4 |" in md
    assert "### Table II" in md and "planner control study" in md and "### Table III" in md
    assert "simulated VLM error model `nominal`; 2 tasks x 2 runs" in md and "Wall time: 12 s" in md


def test_rows_without_episodes_show_na(tmp_path):
    cfg = load_config(write_config(tmp_path))
    t = build_tables(cfg, {"sim:nominal": []})
    assert all(r["SR"] is None and r["episodes"] == 0 for r in t["table2"])
    assert "| PIVOT | 0 | n/a | n/a | n/a | n/a | 10.3 |" in format_markdown(t)


def test_main_from_runs_writes_markdown_and_json(tmp_path, capsys):
    cfg_path = write_config(tmp_path)
    cfg = load_config(cfg_path)
    write_runs(cfg, tmp_path / "runs")
    assert main(["--config", str(cfg_path), "--from-runs", str(tmp_path / "runs"), "--json", str(tmp_path / "t.json")]) == 0
    md = (tmp_path / "runs" / "paper_tables.md").read_text()
    assert capsys.readouterr().out == md + "\n"
    assert "| OnFly (ours) | 4 | 100.0 | 100.0 | 0.0 | 20.0 | 67.8 | 78.1 | 2.7 | 27.1 |" in md
    data = json.loads((tmp_path / "t.json").read_text())
    assert data["table2"][3]["SR"] == 100.0 and data["error_model"] == "nominal"


def test_config_errors(tmp_path):
    with pytest.raises(PaperTablesError, match="must include bench.vlm"):
        load_config(write_config(tmp_path, backbones='[["sim:weak", "2B"]]'))
    with pytest.raises(PaperTablesError, match="unknown field"):
        load_config(write_config(tmp_path, extra="[paper_tables.extra]\nx = 1"))
    with pytest.raises(PaperTablesError, match="list of \\[vlm spec, label\\] pairs"):
        load_config(write_config(tmp_path, backbones='["sim:nominal"]'))
    assert main(["--config", str(tmp_path / "missing.toml")]) == 2


def test_run_all_runs_each_backbone_into_its_folder(tmp_path, monkeypatch):
    # the runner is exercised by its own tests; here: which configs go where
    calls = []

    class Res:
        records: list = []
        wall_s = 1.5

    def fake_run_bench(bench, out, workers=None, progress=False):
        calls.append((bench.vlm, bench.methods, Path(out).name, workers))
        return Res()

    monkeypatch.setattr("experiments.paper_tables.run_bench", fake_run_bench)
    cfg = load_config(write_config(tmp_path))
    _, walls = run_all(cfg, tmp_path / "out", workers=2, progress=False)
    assert calls[0][0] == "sim:nominal" and len(calls[0][1]) == 10 and calls[0][2] == "nominal"
    assert sorted(c[:3] for c in calls[1:]) == [("sim:strong", ("onfly",), "strong"), ("sim:weak", ("onfly",), "weak")]
    assert all(c[3] == 2 for c in calls) and walls == {"sim:nominal": 1.5, "sim:weak": 1.5, "sim:strong": 1.5}


def test_task_chunks_mix_the_order_and_cover_every_task_once():
    ids = [f"{scene}-{kind}{k:02d}" for scene in ("a", "b", "c") for kind in ("o", "p") for k in range(1, 9)]
    chunks = task_chunks(ids, 10)
    assert len(chunks) == 5 and sorted(len(c) for c in chunks) == [9, 9, 10, 10, 10]
    assert sorted(sum(chunks, [])) == sorted(ids)
    assert chunks == task_chunks(list(reversed(ids)), 10)  # the order depends on the ids only
    # a file's grouping by kind does not survive: every chunk holds both kinds and 3 scenes
    assert all({t.split("-")[1][0] for t in c} == {"o", "p"} and len({t[0] for t in c}) == 3 for c in chunks)
    assert task_chunks(ids, None) == [ids] and task_chunks(ids, 50) == [ids]


def test_chunked_run_runs_every_backbone_per_chunk_then_the_whole_selection(tmp_path, monkeypatch):
    calls = []

    class Res:
        records: list = []
        wall_s = 1.0

    def fake_run_bench(bench, out, workers=None, progress=False):
        calls.append((bench.vlm, bench.task_ids, Path(out).name))
        return Res()

    monkeypatch.setattr("experiments.paper_tables.run_bench", fake_run_bench)
    cfg = load_config(write_config(tmp_path))
    cfg = type(cfg)(cfg.bench, cfg.backbones, 1, cfg.source)
    _, walls = run_all(cfg, tmp_path / "out", progress=False)
    assert [c[:2] for c in calls[:3]] == [("sim:nominal", ("park-o01",)), ("sim:weak", ("park-o01",)), ("sim:strong", ("park-o01",))]
    assert [c[1] for c in calls[3:6]] == [("villa-o01",)] * 3
    assert [c[1] for c in calls[6:]] == [tuple(TASKS)] * 3  # final pass over the whole selection
    assert walls == {"sim:nominal": 3.0, "sim:weak": 3.0, "sim:strong": 3.0}
    with pytest.raises(PaperTablesError, match="chunk_tasks must be a positive integer"):
        type(cfg)(cfg.bench, cfg.backbones, 0, cfg.source)


def test_methods_runs_only_those_rows_and_reads_the_rest_from_the_folder(tmp_path, monkeypatch):
    calls = []

    class Res:
        records: list = []
        wall_s = 2.0

    def fake_run_bench(bench, out, workers=None, progress=False):
        calls.append((bench.vlm, bench.methods))
        return Res()

    monkeypatch.setattr("experiments.paper_tables.run_bench", fake_run_bench)
    cfg = load_config(write_config(tmp_path))
    root = tmp_path / "out"
    write_runs(cfg, root)  # every row already finished in the folder
    records, walls = run_all(cfg, root, progress=False, methods=["typefly", "spf"])
    # only the main VLM runs, only those rows, in the tables' order; no backbone row
    assert calls == [("sim:nominal", ("spf", "typefly"))]
    assert walls == {"sim:nominal": 2.0, "sim:weak": 0.0, "sim:strong": 0.0}
    # the tables still see every finished row of the folder
    assert {r["method"] for r in records["sim:nominal"]} == set(cfg.main_methods)
    assert len(records["sim:weak"]) == 2 * len(TASKS)
    calls.clear()
    run_all(cfg, root, progress=False, methods=["onfly"])  # the backbone method runs everywhere
    assert sorted(calls) == [("sim:nominal", ("onfly",)), ("sim:strong", ("onfly",)), ("sim:weak", ("onfly",))]
    with pytest.raises(PaperTablesError, match="unknown method"):
        check_methods(cfg, ["onfly", "rt2"])
    assert main(["--config", str(tmp_path / "pt.toml"), "--methods", "nope", "--from-runs", str(root)]) == 2
