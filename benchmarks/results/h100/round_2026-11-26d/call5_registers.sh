#!/usr/bin/env bash
# registers of the cart-pole kernel under experiment switches: compile in parallel (cache), then ncu one by one
export JAXROBO_CACHE_DIR=/tmp/jcx XLA_PYTHON_CLIENT_PREALLOCATE=false
B=benchmarks/randomisation_cost.py
L=benchmarks/results/h100/round_2026-11-26c/lane_resets.py
EXPS=(base:: nofirst:no_first_noise: nostep:no_step_noise: nonoise:no_first_noise,no_step_noise: nofactors:no_factors: lane::L lane_nonoise:no_first_noise,no_step_noise:L)
go() {  # name exp script [ncu]
  local cmd="python3 $3 --device gpu --envs CartPoleStayUp-v0 --n-envs 16384 --nepisodes 2 --repeats 1 --variants kernel-physics-only"
  if [ -n "$4" ]; then
    JAXROBO_KERNEL_EXPERIMENT="$2" /usr/local/cuda/bin/ncu --kernel-name regex:cartpole --launch-count 1 --section LaunchStats --section Occupancy $cmd > $OUT/x_$1.txt 2>&1
    echo "$1: $(grep -E 'Registers Per Thread' $OUT/x_$1.txt | awk '{print $NF}') regs; $(grep -E 'Theoretical Occupancy' $OUT/x_$1.txt | awk '{print $NF}') %"
  else
    JAXROBO_KERNEL_EXPERIMENT="$2" $cmd > $OUT/c_$1.txt 2>&1 || echo "$1 compile failed"
  fi
}
for e in "${EXPS[@]}"; do IFS=: read n x s <<< "$e"; s=${s:+$L}; go $n "$x" ${s:-$B} & done; wait
echo compiled $(date)
for e in "${EXPS[@]}"; do IFS=: read n x s <<< "$e"; s=${s:+$L}; go $n "$x" ${s:-$B} ncu; done
