"""Copy an unfinished tables-of-record run into the repository as append-only chunks.

A machine may be new at the next session (only main survives), so the run's finished episodes
are kept in main under record-in-progress/ until the run is whole. Each save adds, per pool, one
gzip chunk with the complete lines written since the last save; restore_partial.py rebuilds the
run folder from the chunks.

    python save_partial.py RUN_DIR REPO_DIR
"""
import gzip, json, shutil, sys, time
from pathlib import Path

run, repo = Path(sys.argv[1]), Path(sys.argv[2])
dest = repo / "record-in-progress"
total = 0
for pool in sorted((run / "pools").iterdir()):
    src = pool / "episodes.jsonl"
    if not src.exists():
        continue
    data = src.read_bytes()
    data = data[: data.rfind(b"\n") + 1]
    lines = data.splitlines(keepends=True)
    pdir = dest / "pools" / pool.name
    pdir.mkdir(parents=True, exist_ok=True)
    shutil.copy2(pool / "config.json", pdir / "config.json")
    chunks = sorted(pdir.glob("chunk-*.jsonl.gz"))
    saved = sum(len(gzip.decompress(c.read_bytes()).splitlines()) for c in chunks)
    total += len(lines)
    if len(lines) > saved:
        (pdir / f"chunk-{len(chunks):03d}.jsonl.gz").write_bytes(gzip.compress(b"".join(lines[saved:]), mtime=0))
shutil.copy2(run / "run_state.json", dest / "run_state.json")
if (run / "machines.log").exists():
    shutil.copy2(run / "machines.log", dest / "machines.log")
(dest / "SAVED").write_text(f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())} {total} episodes\n")
print(f"saved {total} episodes")
