#!/usr/bin/env bash
# domain_in_memory.patch: the drawn domain and noise key in the output block instead of the step's carry.
# Compile (and probe the values) in parallel, then registers (ncu) and timings, alternating with the committed tree.
set -u
R=$PWD; HERE=$R/benchmarks/results/h100/round_2026-11-26e
export JAXROBO_CACHE_DIR=/tmp/jc
rm -rf /tmp/M && mkdir /tmp/M && cp -r jaxrobo envs agents benchmarks pyproject.toml /tmp/M/
(cd /tmp/M && git apply $HERE/domain_in_memory.patch) || { echo "patch failed"; exit 1; }
B=benchmarks/randomisation_cost.py
SMALL="--device gpu --envs CartPoleStayUp-v0 --n-envs 16384 --nepisodes 2 --repeats 1"
BIG="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
bg() { local d=$1 tag=$2; shift 2
  (cd $d && XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=/tmp/site:$d "$@" > $OUT/warm_$tag.txt 2>&1 || echo "$tag failed") & }
T0=$(date +%s)
bg /tmp/M M_small python3 $B $SMALL --variants kernel-physics-only
bg /tmp/M M_big python3 $B $BIG --repeats 1 --variants kernel-nominal,kernel-physics-only
bg /tmp/M M_values python3 $HERE/values_probe.py
bg $R E_big python3 $B $BIG --repeats 1 --variants kernel-nominal,kernel-physics-only
wait; echo "compiled: $(( $(date +%s) - T0 )) s"
echo "values M: $(tail -1 $OUT/warm_M_values.txt | cut -c1-400)"
(cd /tmp/M && PYTHONPATH=/tmp/site:/tmp/M python3 benchmarks/kernel_occupancy.py --n-envs 16384 --nepisodes 2 \
   --variants kernel-physics-only --out $OUT/occupancy_M.json 2>&1 | grep -v Warning | tail -2)
echo "ncu: $(( $(date +%s) - T0 )) s"
for t in M E M; do
  d=$R; [ $t = M ] && d=/tmp/M
  echo "== $t"
  (cd $d && PYTHONPATH=/tmp/site:$d python3 $B $BIG --repeats 3 --variants kernel-nominal,kernel-physics-only,kernel-randomised \
     --out $OUT/times6_${t}_$(date +%s).json  # kept as times6_M_1, times6_E, times6_M_2 2>&1 | grep -v Warning | tail -5 | cut -c1-100)
done
echo "all: $(( $(date +%s) - T0 )) s"
