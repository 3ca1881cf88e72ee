#!/bin/bash
# Land the whole run in main: results/, the README's results sections, the test that guards them,
# and record-in-progress/ removed (its pending patches kept in /work/pending). Commits nothing:
# review `git status` / `git diff`, run the tests, then commit.
#   bash /work/tools/land.sh SESSIONS     (SESSIONS: how many sessions flew the run)
set -euo pipefail
SESSIONS=${1:?usage: land.sh SESSIONS}
RUN=${RUN:-/work/record/r10}; WT=${WT:-/work/wt/r10}; MAIN=${MAIN:-/work/main}  # overridable for a dry run
if pgrep -f "tables_of_record.py .*--out $RUN" > /dev/null; then echo "the run is still going" >&2; exit 1; fi
cd "$WT"
.venv/bin/python experiments/tables_of_record.py --manifest experiments/configs/tables_of_record.toml \
  --out "$RUN" --from-runs > "$RUN/final.md" 2> "$RUN/final.log"
if grep -q "^incomplete:" "$RUN/final.log"; then
  grep "^incomplete:" "$RUN/final.log" >&2
  [ "${ALLOW_INCOMPLETE:-0}" = 1 ] || exit 1  # a dry run on a partial snapshot only
fi
cd "$MAIN"
mkdir -p results /work/pending
cp "$RUN"/records.jsonl.gz "$RUN"/tables.md "$RUN"/tables.json "$RUN"/run_state.json "$RUN"/machines.log results/
cp record-in-progress/drafts_outside/results_README.md results/README.md
cp -r record-in-progress/pending/. /work/pending/ 2> /dev/null || true
python3 record-in-progress/tools/assemble.py README.md record-in-progress/drafts "$RUN" --sessions "$SESSIONS" \
  --history docs/results_history.md --replace record-in-progress/drafts_outside/replacements.txt
git mv record-in-progress/drafts_tests/test_results_of_record.py tests/test_results_of_record.py
git rm -r -q record-in-progress
.venv/bin/python experiments/print_tables.py results/records.jsonl.gz --embedded README.md
.venv/bin/python -m pytest -q tests/test_results_of_record.py || [ "${ALLOW_INCOMPLETE:-0}" = 1 ]
if grep -rln "record-in-progress" --include=*.md --include=*.py --include=*.sh --include=*.toml . | grep -v "^./.venv"; then
  echo "the files above still name record-in-progress/" >&2
fi
git add results docs/results_history.md README.md tests/test_results_of_record.py
echo "landed in the index (not committed); pending patches in /work/pending"
