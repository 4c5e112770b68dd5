#!/usr/bin/env bash
# The committed tree (erfinv for registers): the kernel tests on the GPU while the timed programs compile, then
# every variant timed in two processes (the spread between processes).
set -u
export JAXROBO_CACHE_DIR=/tmp/jc
B=benchmarks/randomisation_cost.py
BIG="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
V=kernel-nominal,kernel-physics-only,kernel-pinned,kernel-randomised
T0=$(date +%s)
(XLA_PYTHON_CLIENT_PREALLOCATE=false python3 $B $BIG --repeats 1 --variants $V > /dev/null 2>&1 || echo "warm failed") &
JAX_PLATFORMS=cuda XLA_PYTHON_CLIENT_PREALLOCATE=false timeout 420 python3 -m pytest -q -p no:cacheprovider -n 12 \
  tests/test_fused_pallas.py tests/test_randomise_kernels.py > $OUT/kernel_tests_gpu.txt 2>&1
echo "tests rc=$? $(tail -1 $OUT/kernel_tests_gpu.txt)"
wait; echo "tests and compile: $(( $(date +%s) - T0 )) s"
for round in 1 2; do
  echo "== round $round"
  python3 $B $BIG --repeats 3 --variants $V --out $OUT/times_committed_$round.json 2>&1 | grep -v Warning | tail -7 | cut -c1-110
done
echo "all: $(( $(date +%s) - T0 )) s"
