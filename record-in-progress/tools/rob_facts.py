"""Robustness facts from the pools: per method, lost/gained tasks ideal -> realistic with end
reasons, indoor/outdoor split, paths of tasks solved in both, decision failure counts.
    python rob_facts.py RUN_DIR [method ...]
"""
import collections, json, sys
from pathlib import Path

run = Path(sys.argv[1]); want = sys.argv[2:]
INDOOR = {"corridor", "factory_hall", "warehouse"}
def load(prefix):
    out = {}
    for p in (run / "pools").glob(prefix + "*"):
        for l in open(p / "episodes.jsonl"):
            try: r = json.loads(l)
            except ValueError: continue
            if r["run"] == 0: out[(r["method"], r["task"])] = r
    return out
I, R = load("nominal-ideal-"), load("nominal-realistic-")
methods = sorted({m for m, _ in R}, key=lambda m: m) if not want else want
for m in methods:
    keys = [k for k in R if k[0] == m and k in I]
    if not keys: continue
    lost = [k for k in keys if I[k]["metrics"]["success"] and not R[k]["metrics"]["success"]]
    gained = [k for k in keys if R[k]["metrics"]["success"] and not I[k]["metrics"]["success"]]
    both = [k for k in keys if R[k]["metrics"]["success"] and I[k]["metrics"]["success"]]
    why = collections.Counter(R[k].get("failure") or R[k]["end_reason"] for k in lost)
    print(f"== {m}: pairs {len(keys)} SR {sum(I[k]['metrics']['success'] for k in keys)} -> {sum(R[k]['metrics']['success'] for k in keys)}; lost {len(lost)} {dict(why)}; outdoor lost {sum(1 for k in lost if I[k]['scene'] not in INDOOR)}; gained {len(gained)}: {' '.join(k[1] for k in gained)}")
    print("   lost: " + " ".join(f"{k[1]}[{R[k].get('failure') or R[k]['end_reason']} {R[k]['metrics']['navigation_error_m']:.1f}m {R[k]['metrics']['flight_time_s']:.0f}s; ideal {I[k]['metrics']['flight_time_s']:.0f}s]" for k in sorted(lost)))
    for grp, name in ((lambda s: s not in INDOOR, "outdoor"), (lambda s: s in INDOOR, "indoor")):
        g = [k for k in both if grp(I[k]["scene"])]
        if g:
            pi = sum(I[k]["metrics"]["path_length_m"] for k in g) / len(g); pr = sum(R[k]["metrics"]["path_length_m"] for k in g) / len(g)
            fi = sum(I[k]["metrics"]["flight_time_s"] for k in g) / len(g); fr = sum(R[k]["metrics"]["flight_time_s"] for k in g) / len(g)
            print(f"   solved both {name} {len(g)}: path {pi:.1f} -> {pr:.1f} m, FT {fi:.1f} -> {fr:.1f} s")
    df = lambda D: sum((D[k].get("method_summary") or {}).get("decision_failures", {}).get("no depth at the pixel", 0) for k in keys)
    print(f"   'no depth at the pixel' decisions ideal {df(I)} realistic {df(R)}; min clear realistic {min(R[k]['min_clearance_m'] for k in keys):.2f}")
    col = [k for k in keys if R[k]["metrics"]["collided"]]
    if col and m.startswith(("onfly", "spf_planner")):
        print("   collisions: " + " ".join(f"{k[1]} {json.dumps(R[k].get('collision'))[:200]}" for k in col))
