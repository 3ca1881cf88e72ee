#!/bin/bash
# The tables of record, table by table (resumable). Order: tables not yet drafted first.
cd /work/wt/r10
OUT=/work/record/r10
# Which machine and numerical stack fly this session's episodes (episodes reproduce record for
# record on one CPU and one package set; across them a few go another way).
echo "$(date -u +%FT%TZ) session start: cpu=$(lscpu | sed -n 's/^Model name: *//p' | tr ' ' '_') flags_sha=$(grep -m1 flags /proc/cpuinfo | sha256sum | cut -c1-12) freeze_sha=$(.venv/bin/pip freeze --exclude-editable 2>/dev/null | sha256sum | cut -c1-12) blas=$(.venv/bin/python -c 'import threadpoolctl,numpy;print([(i["internal_api"],i.get("architecture")) for i in threadpoolctl.threadpool_info()])' 2>/dev/null | tr -d ' ')" >> $OUT/machines.log
for t in robustness table3_architecture table3_memory planner_study table3_backbone tracking table2 search_ablation hard_vs_150; do
  for attempt in 1 2 3; do
    echo "$(date -u +%FT%T) start $t attempt $attempt" >> $OUT/chain.log
    .venv/bin/python experiments/tables_of_record.py --manifest experiments/configs/tables_of_record.toml \
      --out $OUT --workers 2 --tables $t >> $OUT/run.log 2>&1 && break
    echo "$(date -u +%FT%T) $t failed rc=$?" >> $OUT/chain.log
    sleep 5
  done
done
echo "$(date -u +%FT%T) chain done" >> $OUT/chain.log
