#!/usr/bin/env bash
# the randomised kernel with ptxas' register cap (XLA's --xla_gpu_asm_extra_flags): compile in parallel, time one by one
export JAXROBO_CACHE_DIR=/tmp/jcy
B=benchmarks/results/h100/round_2026-11-26d/capped.py
V=kernel-nominal,kernel-physics-only,kernel-randomised
args="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
for cap in 0 96 128; do
  f=""; [ $cap != 0 ] && f="--maxrregcount=$cap"
  XLA_PYTHON_CLIENT_PREALLOCATE=false PTXAS_FLAGS="$f" python3 $B $args --repeats 1 --variants $V > $OUT/warm_$cap.txt 2>&1 &
done
wait; echo compiled $(date)
f="--maxrregcount=96"
PTXAS_FLAGS="$f" JAXROBO_CACHE_DIR=/tmp/jcz /usr/local/cuda/bin/ncu --kernel-name regex:cartpole --launch-count 1 --section LaunchStats --section Occupancy python3 $B --device gpu --envs CartPoleStayUp-v0 --n-envs 16384 --nepisodes 2 --repeats 1 --variants kernel-physics-only > $OUT/ncu_cap96.txt 2>&1
grep -E "Registers Per|Theoretical Occ|spill" $OUT/ncu_cap96.txt
for cap in 0 96 128; do
  f=""; [ $cap != 0 ] && f="--maxrregcount=$cap"
  echo "cap $cap"; PTXAS_FLAGS="$f" python3 $B $args --repeats 3 --variants $V --out $OUT/time_cap$cap.json 2>&1 | grep -E "M steps/s|cost" | sed 's/ExecutionPlan.*//'
done
