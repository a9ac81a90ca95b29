#!/bin/bash
# 20 runs of the Ctrl-C and SIGTERM tests, in a non-interactive shell's background job (SIGINT ignored, as the suite may be)
# run as: bash -c "bash results/trials/cluster/stop_loop/run.sh &"  (the background job inherits SIGINT ignored)
cd "$(git rev-parse --show-toplevel)"
start=$(date +%s)
pass=0; fail=0
for i in $(seq 1 20); do
  s=$(date +%s)
  if PYTHONPATH=. timeout 900 ${PYTHON:-python} -m pytest -q -x -p no:cacheprovider tests/cloud/cluster/test_local.py -k runs_until_stopped > results/trials/cluster/stop_loop/run-$i.log 2>&1; then pass=$((pass+1)); r=pass; else fail=$((fail+1)); r=FAIL; fi
  echo "run $i: $r in $(( $(date +%s) - s )) s ($(tail -1 results/trials/cluster/stop_loop/run-$i.log))" >> results/trials/cluster/stop_loop/summary.txt
done
echo "total: $pass passed, $fail failed, $(( $(date +%s) - start )) s" >> results/trials/cluster/stop_loop/summary.txt
