"""Print the tables of record from their records file alone (no episode runs again).

``experiments/tables_of_record.py`` writes ``DIR/records.jsonl.gz``: a gzip of JSON lines, the
first line a header (the format tag, the manifest's tables with their sets, row labels and the
paper's numbers, the code digest and commit of the episodes, the wall time spent per table),
then one compact line per episode (:data:`RECORD_FIELDS`). This module turns those lines into
the tables (:func:`build_tables`) and the tables into markdown (:func:`format_document`,
:func:`format_table`); the command writes ``DIR/tables.md`` and ``DIR/tables.json`` with these
same functions from the file it has just written, so what this prints is what it wrote.

A table whose two sets differ only in their realism profile (the robustness table: every
method in the ideal world and in the realistic one) also gets a side-by-side view: per method,
SR and CR in each world over the same (task, run) pairs, and how many episodes were lost
(succeeded in the first world, failed in the second, counted by the second's end reason) and
gained.

Run::

    .venv/bin/python experiments/print_tables.py runs/record/records.jsonl.gz [--table NAME] [--format md|json]
    .venv/bin/python experiments/print_tables.py runs/record/records.jsonl.gz --embedded README.md [--write]

Without ``--table`` it prints every table (``tables.md`` byte for byte); ``--table NAME``
prints that table's section of it. ``--failures`` prints instead, per row, the episodes that
failed, grouped by how they failed (``failure``: ``collision``, ``time_limit``,
``stopped_outside_radius`` ...), each as ``task/run``: the ids a reader looks up to explain a
row, and ``--method NAME`` keeps one method's rows. ``--embedded README.md`` checks the tables a
markdown file embeds (each between a line ``<!-- table of record: NAME -->`` and a line ``<!-- end
of table of record -->``, as :func:`format_table` prints it with a ``####`` heading) against the
records: exit 0 when every one is equal, 1 with a diff when one is not; ``--write`` rewrites them.
Only the standard library is used: printing needs no simulator.
"""

from __future__ import annotations

import argparse
import difflib
import gzip
import json
import sys
import zlib
from pathlib import Path
from typing import Any, Iterable, Sequence

__all__ = [
    "FORMAT",
    "RECORD_FIELDS",
    "END_REASONS",
    "RecordsFileError",
    "read_records_file",
    "build_tables",
    "format_table",
    "format_document",
    "tables_json",
    "failed_episodes",
    "format_failures",
    "EMBED_BEGIN",
    "EMBED_END",
    "EmbedError",
    "embedded_tables",
    "fill_embedded",
    "main",
]

#: Tag of the header line; a file with another tag is refused.
FORMAT = "onfly-tables-of-record/1"

#: Fields of an episode line (``track`` only on tracking tasks, ``start_in_view`` only when a
#: table it belongs to splits by it, ``error`` only on a method error).
RECORD_FIELDS = (
    "key", "tables", "method", "task", "scene", "kind", "run", "seed", "vlm", "error_model", "realism",
    "metrics", "end_reason", "failure", "sim_s", "wall_s", "cpu_s", "min_clearance_m", "track", "start_in_view", "error",
)  # fmt: skip

#: End reasons in the order the tables list them (as :data:`onfly.bench.episode.END_REASONS`).
END_REASONS = ("stopped", "collision", "time_limit", "out_of_bounds", "method_error")


class RecordsFileError(ValueError):
    """A records file that cannot be read as tables of record (names the file and the fault)."""


def read_records_file(path: str | Path) -> tuple[dict, list[dict]]:
    """The header and the episode records of a ``records.jsonl.gz``.

    Raises RecordsFileError when the file is missing, not gzip, lacks the header line or
    holds a line that is not JSON.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordsFileError(f"records file not found: {path}")
    try:
        with gzip.open(path, "rt", encoding="utf-8") as f:
            lines = [line for line in f if line.strip()]
    except (OSError, EOFError, zlib.error, UnicodeDecodeError) as exc:
        raise RecordsFileError(f"{path}: not a gzip file of JSON lines ({exc})") from None
    rows = []
    for n, line in enumerate(lines, 1):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise RecordsFileError(f"{path}:{n}: not JSON ({exc})") from None
    if not rows or not isinstance(rows[0], dict) or rows[0].get("format") != FORMAT:
        found = rows[0].get("format") if rows and isinstance(rows[0], dict) else None
        raise RecordsFileError(f"{path}: the first line must be the header with format {FORMAT!r}, found {found!r}")
    return rows[0], rows[1:]


# -- statistics ------------------------------------------------------------------------------------


def _mean(xs: Sequence[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None


def _pct(xs: Sequence[bool]) -> float | None:
    m = _mean([float(bool(x)) for x in xs])
    return None if m is None else 100.0 * m


def _end_reasons(recs: Iterable[dict]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for r in recs:
        counts[r["end_reason"]] = counts.get(r["end_reason"], 0) + 1
    order = {k: i for i, k in enumerate(END_REASONS)}
    return dict(sorted(counts.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0])))


def _view(recs: list[dict]) -> dict:
    """SR % and episodes with the goal in view at the start and out of view."""
    seen = [r for r in recs if r.get("start_in_view") is True]
    hidden = [r for r in recs if r.get("start_in_view") is False]
    return {
        "in_view_episodes": len(seen),
        "SR_in_view": _pct([r["metrics"]["success"] for r in seen]),
        "out_of_view_episodes": len(hidden),
        "SR_out_of_view": _pct([r["metrics"]["success"] for r in hidden]),
    }


def _track(recs: list[dict]) -> dict:
    """Means over the tracking episodes: time in band %, band error m, times lost and re-found,
    and stop held % (of the episodes whose task asks for a stop; None when none does)."""
    ts = [r["track"] for r in recs if r.get("track")]
    stops = [t["stop_ok"] for t in ts if t.get("stop_ok") is not None]
    in_band = _mean([t["in_band_frac"] for t in ts])
    return {
        "episodes": len(ts),
        "in_band_pct": None if in_band is None else 100.0 * in_band,
        "band_error_m": _mean([t["band_error_m"] for t in ts]),
        "lost": _mean([t["times_lost"] for t in ts]),
        "refound": _mean([t["times_refound"] for t in ts]),
        "stop_held_pct": _pct(stops),
    }


def _row(table: dict, part_index: int, method: str, recs: list[dict]) -> dict:
    """One row: a method on one set of a table (SR / OSR / CR in %, FT s, NE m, SPL in [0, 1],
    and ``min_clearance_m``: the smallest exact distance from the vehicle's centre to the scene
    over its episodes, metres, from the truth; the body's radius is 0.25 m, so a collided
    episode reads below it)."""
    part = table["parts"][part_index]
    label = table["labels"].get(method, method)
    ms = [r["metrics"] for r in recs]
    row: dict[str, Any] = {
        "set": part["label"],
        "part": part_index,
        "method": method,
        "label": label,
        "error_model": part["error_model"],
        "realism": part["realism"],
        "episodes": len(recs),
        "planned": part["tasks"] * part["runs"],
        "SR": _pct([m["success"] for m in ms]),
        "OSR": _pct([m["oracle_success"] for m in ms]),
        "CR": _pct([m["collided"] for m in ms]),
        "FT": _mean([m["flight_time_s"] for m in ms]),
        "NE": _mean([m["navigation_error_m"] for m in ms]),
        "SPL": _mean([m["spl"] for m in ms]),
        "min_clearance_m": min((c for r in recs if (c := r.get("min_clearance_m")) is not None), default=None),
        "end_reasons": _end_reasons(recs),
    }
    if table["paper"]:
        nums = table["paper_numbers"].get(part.get("paper_row") or label)
        row["paper"] = None if nums is None else dict(zip(("SR", "OSR", "CR", "FT"), nums))
    if table["split_view"]:
        row["view"] = _view(recs)
    if table["track"]:
        row["track"] = _track(recs)
    return row


def _paired_parts(table: dict) -> tuple[int, int] | None:
    """The two sets of a table that differ only in their realism profile (same methods, error
    model and task count), ideal first: the table compares one world against the other."""
    parts = table["parts"]
    if len(parts) != 2:
        return None
    a, b = parts
    same = a["methods"] == b["methods"] and a["error_model"] == b["error_model"] and a["tasks"] == b["tasks"] and a["runs"] == b["runs"]
    if not same or a["realism"] == b["realism"]:
        return None
    return (1, 0) if b["realism"] == "ideal" else (0, 1)


def _paired(table: dict, groups: dict[tuple[int, str], list[dict]]) -> list[dict] | None:
    """Per method, the same task and run in both worlds (:func:`_paired_parts`): episodes that
    succeed in the first and fail in the second (``lost``, counted by the second's end reason)
    and the reverse (``gained``); ``pairs`` is how many (task, run) both sets hold."""
    which = _paired_parts(table)
    if which is None:
        return None
    i, j = which
    out = []
    for m in table["parts"][i]["methods"]:
        first = {(r["task"], r["run"]): r for r in groups.get((i, m), [])}
        second = {(r["task"], r["run"]): r for r in groups.get((j, m), [])}
        both = sorted(first.keys() & second.keys())
        lost = [second[k] for k in both if first[k]["metrics"]["success"] and not second[k]["metrics"]["success"]]
        gained = [k for k in both if second[k]["metrics"]["success"] and not first[k]["metrics"]["success"]]
        out.append({
            "method": m,
            "label": table["labels"].get(m, m),
            "sets": [table["parts"][i]["label"], table["parts"][j]["label"]],
            "pairs": len(both),
            "SR": [_pct([first[k]["metrics"]["success"] for k in both]), _pct([second[k]["metrics"]["success"] for k in both])],
            "CR": [_pct([first[k]["metrics"]["collided"] for k in both]), _pct([second[k]["metrics"]["collided"] for k in both])],
            "lost": len(lost),
            "lost_end_reasons": _end_reasons(lost),
            "gained": len(gained),
        })
    return out


def _table(table: dict, records: list[dict]) -> dict:
    """A table of the header with its rows over the records that belong to it."""
    name = table["name"]
    groups: dict[tuple[int, str], list[dict]] = {}
    mine = []
    for r in records:
        parts = (r.get("tables") or {}).get(name)
        if parts is None:
            continue
        mine.append(r)
        for p in parts:
            groups.setdefault((p, r["method"]), []).append(r)
    rows = [_row(table, i, m, groups.get((i, m), [])) for i, part in enumerate(table["parts"]) for m in part["methods"]]
    cpu = sum(r.get("cpu_s") or 0.0 for r in mine)
    return {
        "name": name,
        "title": table["title"],
        "note": table.get("note", ""),
        "error_models": list(dict.fromkeys(p["error_model"] for p in table["parts"])),
        "realisms": list(dict.fromkeys(p["realism"] for p in table["parts"])),
        "code": table["code"],
        "wall_s": table["wall_s"],
        "episode_cpu_s": cpu,
        "episodes": sum(row["episodes"] for row in rows),
        "planned": sum(row["planned"] for row in rows),
        "parts": table["parts"],
        "columns": {"paper": table["paper"], "split_view": table["split_view"], "track": table["track"]},
        "rows": rows,
        "paired": _paired(table, groups),
    }


def build_tables(header: dict, records: list[dict]) -> dict:
    """Every table of the header, as JSON-able dicts (rows in set order, then method order)."""
    return {
        "format": header["format"],
        "name": header["name"],
        "manifest": header["manifest"],
        "code": header["code"],
        "mixed": header["mixed"],
        "subset": header["subset"],
        "command": header["command"],
        "episodes": len(records),
        "tables": [_table(t, records) for t in header["tables"]],
    }


# -- markdown --------------------------------------------------------------------------------------


def _f(x: float | None, fmt: str = "{:.1f}") -> str:
    return "n/a" if x is None else fmt.format(x)


def _duration(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.2f} h"


def _code_text(code: list[dict], ran: bool) -> str:
    if not code:
        return "unknown (no code version recorded in the folder)"
    text = "; ".join(f"commit `{c['commit']}`, code digest `{c['digest']}`" for c in code)
    if len({c["digest"] for c in code}) > 1:
        text += " (**mixed code versions**)"
    return text if ran else text + " (the folder's; the table itself has not been run, its episodes come from tables that share them)"


def _wall_text(t: dict) -> str:
    cpu = f"episodes' CPU time {_duration(t['episode_cpu_s'])}"
    if t["wall_s"] is None:
        return f"not run by this command; {cpu}"
    return f"{_duration(t['wall_s'])} running this table (an episode it shares with a table run before it counts there); {cpu}"


def _set_text(p: dict) -> str:
    runs = "run" if p["runs"] == 1 else "runs"
    where = f"{p['label']}: " if p["label"] else ""
    return f"{where}`{p['config']}`, {p['tasks']} tasks x {p['runs']} {runs}"


def _header_lines(t: dict) -> list[str]:
    ems = ", ".join(f"`{e}`" for e in t["error_models"])
    rls = ", ".join(f"`{r}`" for r in t["realisms"])
    per = " (per set)" if len(t["parts"]) > 1 else ""
    return [
        f"- simulated-VLM error model: {ems}{per}; realism profile: {rls}{per}",
        f"- code: {_code_text(t['code'], t['wall_s'] is not None)}",
        f"- wall time: {_wall_text(t)}",
        f"- episodes: {t['episodes']} of {t['planned']}; sets: " + "; ".join(_set_text(p) for p in t["parts"]),
    ]


def _cells(t: dict, r: dict) -> list[str]:
    cols = t["columns"]
    cells = [r["set"]] if len(t["parts"]) > 1 else []
    n = str(r["episodes"]) if r["episodes"] == r["planned"] else f"{r['episodes']} of {r['planned']}"
    cells += [r["label"], n, _f(r["SR"]), _f(r["OSR"]), _f(r["CR"]), _f(r["FT"]), _f(r["NE"], "{:.2f}"), _f(r["SPL"], "{:.2f}"),
              _f(r["min_clearance_m"], "{:.2f}")]  # fmt: skip
    if cols["paper"]:
        p = r["paper"] or {}
        cells += [_f(p.get(k)) for k in ("SR", "OSR", "CR", "FT")]
    if cols["split_view"]:
        v = r["view"]
        cells += [f"{_f(v['SR_in_view'])} ({v['in_view_episodes']})", f"{_f(v['SR_out_of_view'])} ({v['out_of_view_episodes']})"]
    if cols["track"]:
        k = r["track"]
        cells += [_f(k["in_band_pct"]), _f(k["band_error_m"], "{:.2f}"), _f(k["lost"], "{:.2f}"), _f(k["refound"], "{:.2f}"),
                  _f(k["stop_held_pct"])]  # fmt: skip
    cells.append(", ".join(f"{k} {v}" for k, v in r["end_reasons"].items()) or "-")
    return cells


def _columns(t: dict) -> tuple[list[str], list[str]]:
    cols = t["columns"]
    names = ["set"] if len(t["parts"]) > 1 else []
    align = ["---"] if names else []
    names += ["method", "episodes", "SR %", "OSR %", "CR %", "FT s", "NE m", "SPL", "min clear m"]
    align += ["---"] + ["---:"] * 8
    extra: list[str] = []
    if cols["paper"]:
        extra += ["paper SR %", "paper OSR %", "paper CR %", "paper FT s"]
    if cols["split_view"]:
        extra += ["SR % goal in view (n)", "SR % out of view (n)"]
    if cols["track"]:
        extra += ["time in band %", "band error m", "lost", "re-found", "stop held %"]
    return names + extra + ["end reasons"], align + ["---:"] * len(extra) + ["---"]


def format_table(t: dict, level: int = 2) -> str:
    """One table's markdown section (a heading of ``level`` hashes, its header lines, the
    table), ending in a newline."""
    names, align = _columns(t)
    lines = [f"{'#' * level} {t['title']} (`{t['name']}`)", ""]
    if t["note"]:
        lines += [t["note"], ""]
    lines += _header_lines(t) + ["", "| " + " | ".join(names) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(_cells(t, r)) + " |" for r in t["rows"]]
    if t.get("paired"):
        lines += _paired_lines(t["paired"])
    return "\n".join(lines) + "\n"


def _paired_lines(rows: list[dict]) -> list[str]:
    a, b = rows[0]["sets"]
    lines = ["", f"The same tasks and runs in both worlds: *lost* succeeded in `{a}` and failed in `{b}` (by their end reason there), "
                 f"*gained* the reverse.", ""]  # fmt: skip
    lines.append(f"| method | pairs | SR % {a} | SR % {b} | CR % {a} | CR % {b} | lost | lost by end reason | gained |")
    lines.append("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |")
    for r in rows:
        why = ", ".join(f"{k} {v}" for k, v in r["lost_end_reasons"].items()) or "-"
        lines.append(f"| {r['label']} | {r['pairs']} | {_f(r['SR'][0])} | {_f(r['SR'][1])} | {_f(r['CR'][0])} | {_f(r['CR'][1])} | "
                     f"{r['lost']} | {why} | {r['gained']} |")  # fmt: skip
    return lines


def format_document(tables: dict) -> str:
    """All tables as markdown: what the command writes to ``tables.md``."""
    lines = [f"# Tables of record: {tables['name']}", ""]
    lines.append(
        f"Manifest `{tables['manifest']}`; {tables['episodes']} episodes; code digest `{tables['code']['digest']}` "
        f"(commit `{tables['code']['commit']}`)."
    )
    lines += ["", f"Command: `{tables['command']}`"]
    lines += ["", "Print a table again from the records alone: `python experiments/print_tables.py DIR/records.jsonl.gz --table NAME`."]
    if tables["subset"]:
        desc = ", ".join(f"{k} {v}" for k, v in tables["subset"].items())
        lines += ["", f"**Subset check ({desc}): not a table of record.**"]
    if tables["mixed"]:
        lines += ["", "**Mixed code versions (`--allow-mixed`): each table names the versions its episodes come from.**"]
    lines.append("")
    return "\n".join(lines) + "\n" + "\n".join(format_table(t) for t in tables["tables"])


def tables_json(tables: dict) -> str:
    """The tables as the JSON text the command writes (``tables.json``, ``--json``)."""
    return json.dumps(tables, indent=1) + "\n"


# -- tables embedded in a markdown file ------------------------------------------------------------

#: The line that opens a table of record embedded in a markdown file (the README); the text up
#: to :data:`EMBED_END` is the table's :func:`format_table` with its heading at
#: :data:`EMBED_LEVEL`, so a reader's copy can be checked against the records.
EMBED_BEGIN = "<!-- table of record: {name} -->"

#: The line that closes an embedded table.
EMBED_END = "<!-- end of table of record -->"

#: Heading level of an embedded table (inside the README's "###" results sections).
EMBED_LEVEL = 4

_BEGIN_HEAD, _BEGIN_TAIL = EMBED_BEGIN.split("{name}")


class EmbedError(ValueError):
    """Markers of embedded tables that do not pair up (names the line)."""


def embedded_tables(text: str) -> list[tuple[str, int, int]]:
    """``(table name, first line, end line)`` of each table embedded in ``text``: the lines
    strictly between its markers, 0-based, ``end`` exclusive, in file order.

    Raises EmbedError on a marker without its pair or a begin marker without a name.
    """
    out: list[tuple[str, int, int]] = []
    open_at: tuple[str, int] | None = None
    for i, line in enumerate(text.splitlines()):
        s = line.strip()
        if s.startswith(_BEGIN_HEAD) and s.endswith(_BEGIN_TAIL):
            name = s[len(_BEGIN_HEAD) : len(s) - len(_BEGIN_TAIL)].strip()
            if open_at is not None:
                raise EmbedError(f"line {i + 1}: table {name!r} begins inside table {open_at[0]!r} (line {open_at[1]})")
            if not name:
                raise EmbedError(f"line {i + 1}: a table of record marker without a table name")
            open_at = (name, i + 1)
        elif s == EMBED_END:
            if open_at is None:
                raise EmbedError(f"line {i + 1}: an end marker with no table open")
            out.append((open_at[0], open_at[1], i))
            open_at = None
    if open_at is not None:
        raise EmbedError(f"line {open_at[1]}: table {open_at[0]!r} is never closed ({EMBED_END!r})")
    return out


def fill_embedded(text: str, tables: dict, spans: list[tuple[str, int, int]] | None = None) -> str:
    """``text`` with every embedded table replaced by the table built from the records
    (:func:`format_table` at :data:`EMBED_LEVEL`); the rest of the text is kept as it is.
    ``spans``: :func:`embedded_tables` of ``text`` when the caller already has them.

    Raises EmbedError on unpaired markers and KeyError naming a table the records do not hold.
    """
    by_name = {t["name"]: t for t in tables["tables"]}
    lines = text.splitlines(keepends=True)
    out: list[str] = []
    pos = 0
    for name, first, end in embedded_tables(text) if spans is None else spans:
        if name not in by_name:
            raise KeyError(f"no table {name!r} in the records; their tables: {', '.join(by_name)}")
        out += lines[pos:first]
        out.append(format_table(by_name[name], EMBED_LEVEL))
        pos = end
    out += lines[pos:]
    return "".join(out)


# -- failed episodes -------------------------------------------------------------------------------


def failed_episodes(header: dict, records: list[dict], table_name: str, method: str | None = None) -> list[dict]:
    """Per row of a table (set order, then method order; ``method`` keeps one method's rows):
    its set and label, and its failed episodes as ``{failure: ["task/run", ...]}``, failures in
    :data:`END_REASONS` order then by name, ids sorted.

    Raises KeyError naming the table when the header has no such table.
    """
    tables = {t["name"]: t for t in header["tables"]}
    if table_name not in tables:
        raise KeyError(f"no table {table_name!r}; its tables: {', '.join(tables)}")
    table = tables[table_name]
    groups: dict[tuple[int, str], list[dict]] = {}
    for r in records:
        for p in (r.get("tables") or {}).get(table_name) or ():
            groups.setdefault((p, r["method"]), []).append(r)
    order = {k: i for i, k in enumerate(END_REASONS)}
    out = []
    for i, part in enumerate(table["parts"]):
        for m in part["methods"]:
            if method is not None and m != method:
                continue
            by: dict[str, list[str]] = {}
            recs = groups.get((i, m), [])
            for r in recs:
                if not r["metrics"]["success"]:
                    by.setdefault(r.get("failure") or r["end_reason"], []).append(f"{r['task']}/{r['run']}")
            kinds = sorted(by, key=lambda k: (order.get(k, len(order)), k))
            out.append({"set": part["label"], "method": m, "label": table["labels"].get(m, m), "episodes": len(recs),
                        "failed": {k: sorted(by[k]) for k in kinds}})  # fmt: skip
    return out


def format_failures(table_name: str, rows: list[dict]) -> str:
    """Markdown list of :func:`failed_episodes`: a line per row, then a line per kind of failure."""
    lines = [f"## Failed episodes of `{table_name}` (task/run)", ""]
    for r in rows:
        where = f"{r['set']}: " if r["set"] else ""
        n = sum(len(v) for v in r["failed"].values())
        lines.append(f"- {where}{r['label']}: {n} of {r['episodes']} failed")
        lines += [f"  - {k} {len(v)}: " + ", ".join(v) for k, v in r["failed"].items()]
    return "\n".join(lines) + "\n"


# -- command line ----------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("records", help="DIR/records.jsonl.gz written by experiments/tables_of_record.py")
    ap.add_argument("--table", default=None, metavar="NAME", help="print only this table (default: every table)")
    ap.add_argument("--format", default="md", choices=("md", "json"), help="markdown (as tables.md) or JSON (as tables.json)")
    ap.add_argument("--failures", action="store_true", help="list each row's failed episodes (task/run) by how they failed")
    ap.add_argument("--method", default=None, metavar="NAME", help="with --failures: only this method's rows")
    ap.add_argument("--embedded", default=None, metavar="MD", help="check the tables embedded in this markdown file (the README) "
                    "against the records: exit 1 and a diff when one differs")  # fmt: skip
    ap.add_argument("--write", action="store_true", help="with --embedded: rewrite the embedded tables from the records")
    args = ap.parse_args(argv)
    if args.method is not None and not args.failures:
        ap.error("--method needs --failures")
    if args.write and args.embedded is None:
        ap.error("--write needs --embedded")
    if args.embedded is not None and (args.failures or args.table is not None or args.format != "md"):
        ap.error("--embedded takes no --failures, --table or --format")
    try:
        header, records = read_records_file(args.records)
    except RecordsFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.failures:
        return _print_failures(header, records, args)
    tables = build_tables(header, records)
    if args.embedded is not None:
        return _check_embedded(tables, Path(args.embedded), write=args.write)
    if args.table is None:
        sys.stdout.write(format_document(tables) if args.format == "md" else tables_json(tables))
        return 0
    by_name = {t["name"]: t for t in tables["tables"]}
    if args.table not in by_name:
        print(f"error: --table: no table {args.table!r} in {args.records}; its tables: {', '.join(by_name)}", file=sys.stderr)
        return 2
    t = by_name[args.table]
    sys.stdout.write(format_table(t) if args.format == "md" else json.dumps(t, indent=1) + "\n")
    return 0


def _check_embedded(tables: dict, path: Path, *, write: bool) -> int:
    try:
        text = path.read_text(encoding="utf-8")
        found = embedded_tables(text)
        filled = fill_embedded(text, tables, found)
    except OSError as exc:
        print(f"error: --embedded: cannot read {path}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except (EmbedError, KeyError) as exc:
        print(f"error: --embedded: {path}: {exc.args[0]}", file=sys.stderr)
        return 2
    if not found:
        print(f"error: --embedded: {path} embeds no table of record (a line {EMBED_BEGIN!r} opens one)", file=sys.stderr)
        return 2
    names = ", ".join(n for n, _, _ in found)
    if filled == text:
        print(f"{path}: {len(found)} embedded tables equal the records ({names})")
        return 0
    if write:
        path.write_text(filled, encoding="utf-8")
        print(f"{path}: rewrote {len(found)} embedded tables from the records ({names})")
        return 0
    diff = difflib.unified_diff(text.splitlines(keepends=True), filled.splitlines(keepends=True), str(path), "from the records")
    sys.stdout.writelines(diff)
    print(f"{path}: embedded tables differ from the records (--write rewrites them)", file=sys.stderr)
    return 1


def _print_failures(header: dict, records: list[dict], args: argparse.Namespace) -> int:
    names = [t["name"] for t in header["tables"]] if args.table is None else [args.table]
    docs, data = [], {}
    for name in names:
        try:
            rows = failed_episodes(header, records, name, args.method)
        except KeyError as exc:
            print(f"error: --table: {exc.args[0]} in {args.records}", file=sys.stderr)
            return 2
        if args.method is not None and not rows:
            if args.table is not None:
                print(f"error: --method: no row of {args.method!r} in table {name!r}", file=sys.stderr)
                return 2
            continue
        docs.append(format_failures(name, rows))
        data[name] = rows
    sys.stdout.write("\n".join(docs) if args.format == "md" else json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
