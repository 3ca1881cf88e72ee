"""Put the drafted results section into the README and fill its tables from the records.

    python assemble.py README.md DRAFTS_DIR RECORDS_DIR --sessions N [--out README.md]

Replaces the README from the line "### Tables of record" up to (not including) the line
"## Measured figures" with DRAFTS_DIR/*.md in name order (the sections it replaces, each named
by the commits it was measured on, go to docs/results_history.md after HISTORY_INTRO), fills @@EPISODES@@, @@WALL@@, @@CPU@@,
@@SIZE@@ and @@SESSIONS@@ from RECORDS_DIR (records.jsonl.gz, run_state.json), then rewrites every
embedded table from the records. Stops on a placeholder left over.

With --replace FILE, also makes exact replacements in the rest of the README (stale figures that
point at the replaced sections). FILE holds blocks

    <<<<
    old text (one or more whole lines)
    ====
    new text
    >>>>

and each old text must occur exactly once outside the replaced range, or nothing is written.
"""
import argparse, gzip, json, re, sys
from pathlib import Path

ap = argparse.ArgumentParser()
ap.add_argument("readme"); ap.add_argument("drafts"); ap.add_argument("records")
ap.add_argument("--sessions", required=True); ap.add_argument("--out", default=None)
ap.add_argument("--history", default=None, help="write the replaced sections here (docs/results_history.md)")
ap.add_argument("--replace", default=None, help="exact replacements outside the replaced range (see the docstring)")
a = ap.parse_args()
repo = Path(a.readme).resolve().parent
sys.path.insert(0, str(repo))
from experiments.print_tables import build_tables, fill_embedded, read_records_file  # noqa: E402

text = Path(a.readme).read_text()
lines = text.splitlines(keepends=True)
start = next(i for i, l in enumerate(lines) if l.rstrip() == "### Tables of record")
end = next(i for i, l in enumerate(lines) if l.rstrip() == "## Measured figures")
body = "\n".join(p.read_text().rstrip("\n") + "\n" for p in sorted(Path(a.drafts).glob("*.md")))
rec = Path(a.records) / "records.jsonl.gz"
state = json.loads((Path(a.records) / "run_state.json").read_text())
with gzip.open(rec, "rt") as f:
    f.readline()
    eps = [json.loads(l) for l in f]


HISTORY_INTRO = """# Results before the tables of record

The README's results sections as they stood before the tables of record were re-run on one
code version (issue 23). Each names the commit it was measured on; every table in it is stale
against the code of the tables of record, which the README shows. They stay here as the record
of how the figures moved, session by session: what each change gained and lost, and why.

"""


def hours(s: float) -> str:
    return f"{s / 3600:.1f} h"


machines = []
if (Path(a.records) / "machines.log").exists():
    for line in (Path(a.records) / "machines.log").read_text().splitlines():
        kv = dict(re.findall(r"(\w+)=(\S+)", line.split("session start:", 1)[1]))
        desc = f"{kv.get('cpu', '?').replace('_', ' ')} (OpenBLAS {re.sub(r'[^A-Za-z0-9]', '', kv.get('blas', '?').split(',')[-1])})"
        if desc not in machines:
            machines.append(desc)
fills = {
    "MACHINES": " and ".join(machines) or "one machine",
    "EPISODES": f"{len(eps):,}",
    "WALL": hours(sum(t["wall_s"] for t in state["tables"].values())),
    "CPU": hours(sum(r.get("cpu_s") or 0.0 for r in eps)),
    "SIZE": f"{rec.stat().st_size / 2**20:.1f} MiB",
    "SESSIONS": a.sessions,
}
body = re.sub(r"@@([A-Z]+)@@", lambda m: fills.get(m.group(1), m.group(0)), body)
left = sorted(set(re.findall(r"@@[A-Z_]+@@", body)))
if left:
    sys.exit(f"placeholders left: {', '.join(left)}")
head, tail = "".join(lines[:start]), "".join(lines[end:])
if a.replace:
    blocks = re.findall(r"^<<<<\n(.*?)^====\n(.*?)^>>>>$", Path(a.replace).read_text(), flags=re.S | re.M)
    if not blocks:
        sys.exit(f"{a.replace}: no <<<< / ==== / >>>> blocks")
    for old, rep in blocks:
        n = head.count(old) + tail.count(old)
        if n != 1:
            sys.exit(f"{a.replace}: found {n} times (must be once):\n{old}")
        head, tail = head.replace(old, rep), tail.replace(old, rep)
new = head + body + "\n" + tail
if a.history:
    old = lines[start:end]
    first = next(i for i, l in enumerate(old) if l.startswith("### ") and i > 0)  # after "Tables of record"
    kept = "".join(l for l in old[first:] if not l.lstrip().startswith("<!-- ")
                   or not (l.strip().startswith("<!-- table of record") or l.strip() == "<!-- end of table of record -->"))
    kept = ("\n" + kept).replace("\n### ", "\n## ").replace("\n#### ", "\n### ").lstrip("\n")
    Path(a.history).write_text(HISTORY_INTRO + kept)
header, records = read_records_file(rec)
new = fill_embedded(new, build_tables(header, records))
Path(a.out or a.readme).write_text(new)
print(f"assembled: {len(eps)} episodes; " + ", ".join(f"{k}={v}" for k, v in fills.items()))
