#!/usr/bin/env bash
# The erfinv written for registers (../round_2026-11-26d/erfinv_for_registers.patch) against the shipped tree, one GPU:
# compile both in parallel, then registers (ncu), values (values_probe.py) and timings one process at a time.
set -u
R=$PWD; HERE=$R/benchmarks/results/h100/round_2026-11-26e
export JAXROBO_CACHE_DIR=/tmp/jc
rm -rf /tmp/p && mkdir /tmp/p && cp -r jaxrobo envs agents benchmarks pyproject.toml /tmp/p/ 2>/dev/null
(cd /tmp/p && git apply benchmarks/results/h100/round_2026-11-26d/erfinv_for_registers.patch) \
  || { echo "patch failed"; exit 1; }
grep -c "_erf_inv(u)" /tmp/p/jaxrobo/speed/fused_pallas.py
B=benchmarks/randomisation_cost.py
ARGS="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
warm() {  # tree tag: compile the timed programs and the probe's
  (cd $1 && XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=/tmp/site:$PWD python3 $B $ARGS --repeats 1 \
     --variants kernel-nominal,kernel-physics-only > $OUT/warm_$2.txt 2>&1) &
  (cd $1 && XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=/tmp/site:$PWD python3 $HERE/values_probe.py \
     > $OUT/values_$2.txt 2>&1) &
}
T0=$(date +%s)
warm $PWD shipped; warm /tmp/p erfinv
wait; echo "compiled and probed: $(( $(date +%s) - T0 )) s"
for t in shipped erfinv; do echo "$t: $(tail -1 $OUT/values_$t.txt)"; done
(cd /tmp/p && PYTHONPATH=/tmp/site:$PWD python3 benchmarks/kernel_occupancy.py --variants kernel-nominal,kernel-physics-only \
   --out $OUT/occupancy_erfinv.json 2>&1 | grep -v Warning | tail -6)
echo "ncu done: $(( $(date +%s) - T0 )) s"
for round in 1 2; do
  for t in shipped erfinv; do
    d=$PWD; [ $t = erfinv ] && d=/tmp/p
    echo "== $t (round $round)"
    (cd $d && PYTHONPATH=/tmp/site:$PWD python3 $B $ARGS --repeats 3 \
       --variants kernel-nominal,kernel-physics-only,kernel-randomised --out $OUT/times_${t}_$round.json 2>&1 \
       | grep -v Warning | tail -5)
  done
done
echo "all: $(( $(date +%s) - T0 )) s"
