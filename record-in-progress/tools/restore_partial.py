"""Rebuild a tables-of-record run folder from record-in-progress/ (see save_partial.py).

    python restore_partial.py REPO_DIR RUN_DIR
"""
import gzip, shutil, sys
from pathlib import Path

repo, run = Path(sys.argv[1]), Path(sys.argv[2])
src = repo / "record-in-progress"
for pdir in sorted((src / "pools").iterdir()):
    out = run / "pools" / pdir.name
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy2(pdir / "config.json", out / "config.json")
    with open(out / "episodes.jsonl", "wb") as f:
        for c in sorted(pdir.glob("chunk-*.jsonl.gz")):
            f.write(gzip.decompress(c.read_bytes()))
shutil.copy2(src / "run_state.json", run / "run_state.json")
if (src / "machines.log").exists():
    shutil.copy2(src / "machines.log", run / "machines.log")
print("restored into", run)
