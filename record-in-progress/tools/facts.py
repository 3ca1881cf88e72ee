"""Facts for the README drafts from a records file (tables_of_record's records.jsonl.gz).

    python facts.py RECORDS TABLE [--set LABEL] [--methods a,b] [--pair A,B] [--pool POOLS_DIR]
Prints per method: SR/CR, failures by kind with ids, split by start in view, time limits that
ended inside the radius; with --pair, the episodes only one of the two methods solved.
"""
import argparse, collections, gzip, json

ap = argparse.ArgumentParser()
ap.add_argument("records"); ap.add_argument("table")
ap.add_argument("--set", default=None); ap.add_argument("--methods", default=None)
ap.add_argument("--pair", default=None); ap.add_argument("--radius", type=float, default=5.0)
a = ap.parse_args()
f = gzip.open(a.records, "rt"); h = json.loads(f.readline())
tab = {t["name"]: t for t in h["tables"]}[a.table]
parts = [p["label"] for p in tab["parts"]]
recs = []
for l in f:
    r = json.loads(l)
    for p in (r.get("tables") or {}).get(a.table, ()):
        if a.set is None or parts[p] == a.set:
            r = dict(r, _set=parts[p]); recs.append(r)
by = collections.defaultdict(list)
for r in recs:
    by[(r["_set"], r["method"])].append(r)
want = a.methods.split(",") if a.methods else None
OUTDOOR = {"urban_block", "villa", "park", "parking_lot", "plaza", "terrace", "duplex"}
for (s, m), rs in by.items():
    if want and m not in want: continue
    n = len(rs); sr = sum(r["metrics"]["success"] for r in rs); cr = sum(r["metrics"]["collided"] for r in rs)
    print(f"== {s} / {m}: {n} eps, SR {100*sr/n:.1f} ({sr}), CR {100*cr/n:.1f} ({cr}), min clear {min(r['min_clearance_m'] for r in rs):.2f}")
    fails = collections.defaultdict(list)
    for r in rs:
        if not r["metrics"]["success"]:
            fails[r.get("failure") or r["end_reason"]].append(r)
    for k, v in sorted(fails.items(), key=lambda kv: -len(kv[1])):
        oov = sum(1 for r in v if r.get("start_in_view") is False)
        inside = [r for r in v if r["metrics"]["navigation_error_m"] <= a.radius]
        outd = sum(1 for r in v if r["scene"] in OUTDOOR)
        print(f"  {k}: {len(v)} (start out of view {oov}; outdoor {outd}; NE<=radius {len(inside)})")
        print("    " + " ".join(sorted(f"{r['task']}/{r['run']}({r['metrics']['navigation_error_m']:.1f})" for r in v)))
    if any("start_in_view" in r for r in rs):
        for flag in (True, False):
            g = [r for r in rs if r.get("start_in_view") is flag]
            if g: print(f"  in view={flag}: {len(g)} eps SR {100*sum(r['metrics']['success'] for r in g)/len(g):.1f}")
if a.pair:
    A, B = a.pair.split(",")
    for s in parts if a.set is None else [a.set]:
        ia = {(r["task"], r["run"]): r for r in by.get((s, A), [])}
        ib = {(r["task"], r["run"]): r for r in by.get((s, B), [])}
        common = sorted(set(ia) & set(ib))
        wa = [k for k in common if ia[k]["metrics"]["success"] and not ib[k]["metrics"]["success"]]
        wb = [k for k in common if ib[k]["metrics"]["success"] and not ia[k]["metrics"]["success"]]
        print(f"== pair {s}: {len(common)} common; only {A}: {len(wa)}; only {B}: {len(wb)}")
        print(f"  only {A}: " + " ".join(f"{t}/{r}[{ib[(t,r)].get('failure') or ib[(t,r)]['end_reason']}]" for t, r in wa))
        print(f"  only {B}: " + " ".join(f"{t}/{r}[{ia[(t,r)].get('failure') or ia[(t,r)]['end_reason']}]" for t, r in wb))
