#!/bin/bash
# Snapshot the running record into /tmp/snap and write its artifacts there (runs nothing).
rm -rf /tmp/snap && mkdir -p /tmp/snap && cp -r /work/record/r10/pools /work/record/r10/run_state.json /tmp/snap/
for f in /tmp/snap/pools/*/episodes.jsonl; do python3 - "$f" <<'P'
import sys; p=sys.argv[1]; d=open(p,'rb').read(); open(p,'wb').write(d[:d.rfind(b"\n")+1])
P
done
cd /work/wt/r10 && .venv/bin/python experiments/tables_of_record.py --manifest experiments/configs/tables_of_record.toml --out /tmp/snap --from-runs > /tmp/snap/fromruns.log 2>&1
tail -2 /tmp/snap/fromruns.log
