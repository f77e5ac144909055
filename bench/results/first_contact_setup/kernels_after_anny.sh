#!/bin/bash
for i in 1 2; do
  for v in A B; do
    d=/tmp/s/setupab/data_$v$i; rm -rf $d
    if [ $v = A ]; then cd /work/main; P=/work/main; else cd /tmp/s/wt; P=/tmp/s/wt; fi
    s=$(date +%s.%N)
    EVA_DATA_DIR=$d PYTHONPATH=$P /work/main/.venv/bin/python -c "from eva_engine.cli.app import app; import eva_engine.cli.setup; app()" setup > /tmp/s/setupab/log_$v$i.txt 2>&1
    e=$(date +%s.%N)
    echo "$v$i $(echo "$e - $s" | bc)" >> /tmp/s/setupab/times.txt
    rm -rf $d
  done
done
echo ALLDONE >> /tmp/s/setupab/times.txt
