#!/usr/bin/env bash
# Groups of eight lanes for a randomised reset (groups_of_eight.patch) against the committed tree: the new tree's
# programs compiled in parallel with its values probe and its registers (ncu), then both trees timed in rounds,
# alternately, in opposite variant orders.
set -u
R=$PWD; HERE=$R/benchmarks/results/h100/round_2026-11-27a
export JAXROBO_CACHE_DIR=/tmp/jc
rm -rf /tmp/p && mkdir /tmp/p && cp -r jaxrobo envs agents benchmarks pyproject.toml /tmp/p/ 2>/dev/null
(cd /tmp/p && git apply -R $HERE/groups_of_eight.patch) || { echo "reverse patch failed"; exit 1; }
grep -c "group_lanes" $R/jaxrobo/speed/fused_pallas.py /tmp/p/jaxrobo/speed/fused_pallas.py
B=benchmarks/randomisation_cost.py
ARGS="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
T0=$(date +%s)
for t in new committed; do
  d=$R; [ $t = committed ] && d=/tmp/p
  for v in kernel-nominal kernel-physics-only kernel-pinned kernel-randomised; do
    (cd $d && XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=/tmp/site:$d python3 $B $ARGS --repeats 1 --variants $v \
       > $OUT/warm_${t}_$v.txt 2>&1 || echo "warm $t $v failed") &
  done
done
(XLA_PYTHON_CLIENT_PREALLOCATE=false python3 $R/benchmarks/results/h100/round_2026-11-26e/values_probe.py \
   > $OUT/values_new.txt 2>&1) &
(XLA_PYTHON_CLIENT_PREALLOCATE=false python3 benchmarks/kernel_occupancy.py --n-envs 16384 --nepisodes 2 \
   --variants kernel-physics-only --out $OUT/occupancy_new.json > $OUT/occupancy_new.txt 2>&1) &
wait; echo "compiled, probed, profiled: $(( $(date +%s) - T0 )) s"
echo "values (new): $(tail -1 $OUT/values_new.txt | cut -c1-400)"
grep -v Warning $OUT/occupancy_new.txt | tail -3 | cut -c1-200
V=kernel-nominal,kernel-physics-only,kernel-pinned,kernel-randomised
VR=kernel-randomised,kernel-pinned,kernel-physics-only,kernel-nominal
for run in "new $V 1" "committed $V 1" "new $VR 2" "committed $VR 2"; do
  set -- $run; d=$R; [ $1 = committed ] && d=/tmp/p
  echo "== $1 ($2)"
  (cd $d && PYTHONPATH=/tmp/site:$d python3 $B $ARGS --repeats 4 --variants $2 --out $OUT/times_${1}_$3.json 2>&1 \
     | grep -v Warning | grep cost | cut -c1-110)
done
echo "all: $(( $(date +%s) - T0 )) s"
