#!/bin/bash
# Every 30 min: add a chunk of the run's new episodes to main's record-in-progress/ and commit it.
while true; do
  sleep 1800
  cd /work/main && python3 /work/tools/save_partial.py /work/record/r10 /work/main > /tmp/autosave.out 2>&1 \
    && git add record-in-progress && git commit -q -m "record-in-progress: $(cat record-in-progress/SAVED | cut -d' ' -f2) episodes of the tables-of-record run (unfinished; kept so the run survives a new machine)" -- record-in-progress >> /tmp/autosave.out 2>&1
done
