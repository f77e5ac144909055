#!/bin/bash
# eva setup into fresh data folders, A (this checkout) and B (a worktree of the variant), alternately:
#   bash kernels_after_anny.sh <worktree of the variant> <scratch folder>
# from the checkout's root, with its venv in .venv; appends "<run> <seconds>" to <scratch>/times.txt.
set -e
MAIN=$PWD
VARIANT=$1
OUT=$2
mkdir -p "$OUT"
for i in 1 2; do
  for v in A B; do
    d=$OUT/data_$v$i; rm -rf "$d"
    if [ $v = A ]; then P=$MAIN; else P=$VARIANT; fi
    s=$(date +%s.%N)
    (cd "$P" && EVA_DATA_DIR=$d PYTHONPATH=$P "$MAIN/.venv/bin/python" -c \
      "from eva_engine.cli.app import app; import eva_engine.cli.setup; app()" setup > "$OUT/log_$v$i.txt" 2>&1)
    e=$(date +%s.%N)
    echo "$v$i $(echo "$e - $s" | bc)" >> "$OUT/times.txt"
    rm -rf "$d"
  done
done
