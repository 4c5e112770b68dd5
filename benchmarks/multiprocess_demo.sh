#!/usr/bin/env bash
# One sweep, sharded two ways on one 2-GPU host, must write the same CSV:
#   1. one process driving both GPUs (a 2-device mesh);
#   2. two processes, one GPU each, joined by jax.distributed (the multi-host path: JAXROBO_COORDINATOR & co.).
# Usage: bash benchmarks/multiprocess_demo.sh [OUT_DIR]       (default runs/multiprocess_demo)
# On a CPU-only machine: DEMO_CPU=1 bash benchmarks/multiprocess_demo.sh  (2 forced host devices per process).
set -uo pipefail
out=${1:-runs/multiprocess_demo}
mkdir -p "$out"
export NCCL_NVLS_ENABLE=0   # keep NVLink multicast off on shared GPU hosts
args=(sweep --env CartPoleStayUp-v0 --grid alpha=0.1,0.3,0.5,0.7 --seeds 64 --n-envs 1 --nepisodes 100 --no-plots --overwrite)
if [ "${DEMO_CPU:-0}" = 1 ]; then
  export JAX_PLATFORMS=cpu
  one_env=(XLA_FLAGS=--xla_force_host_platform_device_count=2)
  per_proc() { echo "XLA_FLAGS=--xla_force_host_platform_device_count=1"; }
else
  one_env=()
  per_proc() { echo "CUDA_VISIBLE_DEVICES=$1"; }
fi
echo "== one process, 2 devices"
env "${one_env[@]}" python -m jaxrobo.cli "${args[@]}" --out "$out/one_process" 2>&1 | grep -v -i warp | tail -4
echo "== two processes, 1 device each, jax.distributed"
port=$((20000 + RANDOM % 20000))
for i in 0 1; do
  env "$(per_proc $i)" JAXROBO_COORDINATOR=localhost:$port JAXROBO_NUM_PROCESSES=2 JAXROBO_PROCESS_ID=$i \
    python -m jaxrobo.cli "${args[@]}" --out "$out/two_processes" > "$out/process$i.log" 2>&1 &
done
wait
grep -v -i warp "$out/process0.log" | grep -E "compiled|rows|best" | head -3
if cmp -s "$out/one_process/sweep.csv" "$out/two_processes/sweep.csv"; then
  echo "sweep.csv identical"
else
  echo "sweep.csv DIFFERS (see $out/process*.log)"; exit 1
fi
