"""Per-method sums of the pilots' method_summary over one table's episodes (joins the records
file's keys with the pools' episodes).

    python summ.py RUN_DIR RECORDS TABLE [--set LABEL]
"""
import argparse, collections, gzip, json, pathlib

ap = argparse.ArgumentParser()
ap.add_argument("run"); ap.add_argument("records"); ap.add_argument("table"); ap.add_argument("--set", default=None)
a = ap.parse_args()
f = gzip.open(a.records, "rt"); h = json.loads(f.readline())
tab = {t["name"]: t for t in h["tables"]}[a.table]
parts = [p["label"] for p in tab["parts"]]
want = {}
for l in f:
    r = json.loads(l)
    for p in (r.get("tables") or {}).get(a.table, ()):
        if a.set is None or parts[p] == a.set:
            want[r["key"]] = (parts[p], r["method"])
acc = collections.defaultdict(lambda: collections.defaultdict(collections.Counter))
n = collections.Counter()
for pool in pathlib.Path(a.run, "pools").iterdir():
    for l in open(pool / "episodes.jsonl"):
        try:
            e = json.loads(l)
        except json.JSONDecodeError:
            continue
        k = want.get(e["key"])
        if k is None:
            continue
        n[k] += 1
        s = e.get("method_summary") or {}
        for name in ("decision_failures", "events", "monitor_statuses", "planner_fallbacks", "search_triggers"):
            acc[k][name].update(s.get(name) or {})
        for name in ("verifier_moved", "goals_clamped", "decisions"):
            acc[k]["totals"][name] += s.get(name) or 0
        acc[k]["vlm_calls"].update(e.get("vlm_calls") or {})
        acc[k]["totals"]["eps_moved>0"] += 1 if (s.get("verifier_moved") or 0) > 0 else 0
for k in sorted(acc):
    print(f"== {k[0]} / {k[1]}: {n[k]} episodes")
    for name, c in acc[k].items():
        print(f"  {name}: " + ", ".join(f"{kk} {vv}" for kk, vv in c.most_common(12)))
