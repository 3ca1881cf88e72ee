#!/bin/bash
# The tables of record, table by table (resumable). Order: tables not yet drafted first.
cd /work/wt/r10
OUT=/work/record/r10
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
