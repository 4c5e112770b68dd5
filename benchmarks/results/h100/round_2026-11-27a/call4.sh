#!/usr/bin/env bash
# The committed tree (groups of eight): the kernel tests on the GPU while the Goto task kernel's variants compile,
# then the Goto case timed in rounds in two processes, in opposite variant orders.
set -u
export JAXROBO_CACHE_DIR=/tmp/jc
B=benchmarks/randomisation_cost.py
ARGS="--device gpu --envs QuadcopterGoto-v2 --n-envs 262144 --nepisodes 200"
T0=$(date +%s)
for v in kernel-nominal kernel-randomised kernel-physics-only; do
  (XLA_PYTHON_CLIENT_PREALLOCATE=false python3 $B $ARGS --repeats 1 --variants $v > /tmp/warm_$v.txt 2>&1 \
     || echo "warm $v failed") &
done
JAX_PLATFORMS=cuda XLA_PYTHON_CLIENT_PREALLOCATE=false timeout 420 python3 -m pytest -q -p no:cacheprovider -n 12 \
  tests/test_fused_pallas.py tests/test_randomise_kernels.py > $OUT/kernel_tests_gpu.txt 2>&1
echo "tests rc=$? $(tail -1 $OUT/kernel_tests_gpu.txt)"
wait; echo "tests and compile: $(( $(date +%s) - T0 )) s"
V=kernel-nominal,kernel-randomised,kernel-physics-only
VR=kernel-physics-only,kernel-randomised,kernel-nominal
for run in "$V 1" "$VR 2"; do
  set -- $run
  echo "== $1"
  timeout 110 python3 $B $ARGS --repeats 2 --variants $1 --out $OUT/goto_times_$2.json 2>&1 | grep -v Warning \
    | grep "cost\|steps/s" | cut -c1-110
done
echo "all: $(( $(date +%s) - T0 )) s"
