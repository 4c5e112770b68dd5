#!/usr/bin/env bash
# Call 2 again without its ncu process, which stalled the parallel phase past the call's limit (ncu beside other
# processes on the GPU): the programs load from call 2's compile cache where the machine kept it. Then both trees
# timed in rounds, alternately, in opposite variant orders, and last the new tree's registers (ncu, alone).
set -u
R=$PWD; HERE=$R/benchmarks/results/h100/round_2026-11-27a
export JAXROBO_CACHE_DIR=/tmp/jc
rm -rf /tmp/p && mkdir /tmp/p && cp -r jaxrobo envs agents benchmarks pyproject.toml /tmp/p/ 2>/dev/null
(cd /tmp/p && git apply -R $HERE/groups_of_eight.patch) || { echo "reverse patch failed"; exit 1; }
B=benchmarks/randomisation_cost.py
ARGS="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
T0=$(date +%s)
for t in new committed; do
  d=$R; [ $t = committed ] && d=/tmp/p
  for v in kernel-nominal kernel-physics-only kernel-pinned kernel-randomised; do
    (cd $d && XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=/tmp/site:$d python3 $B $ARGS --repeats 1 --variants $v \
       > /tmp/warm_${t}_$v.txt 2>&1 || echo "warm $t $v failed") &
  done
done
wait; echo "compiled: $(( $(date +%s) - T0 )) s"
V=kernel-nominal,kernel-physics-only,kernel-pinned,kernel-randomised
VR=kernel-randomised,kernel-pinned,kernel-physics-only,kernel-nominal
for run in "new $V 1" "committed $V 1" "new $VR 2" "committed $VR 2"; do
  set -- $run; d=$R; [ $1 = committed ] && d=/tmp/p
  echo "== $1 ($2)"
  (cd $d && PYTHONPATH=/tmp/site:$d python3 $B $ARGS --repeats 4 --variants $2 --out $OUT/times_${1}_$3.json 2>&1 \
     | grep -v Warning | grep cost | cut -c1-110)
done
echo "timed: $(( $(date +%s) - T0 )) s"
timeout 170 python3 benchmarks/kernel_occupancy.py --n-envs 16384 --nepisodes 2 --variants kernel-physics-only \
  --out $OUT/occupancy_new.json 2>&1 | grep -v Warning | tail -3 | cut -c1-200
echo "all: $(( $(date +%s) - T0 )) s"
