#!/usr/bin/env bash
# registers under experiment switches (compile in parallel, ncu one by one), then timings of the new default
export JAXROBO_CACHE_DIR=/tmp/jcx XLA_PYTHON_CLIENT_PREALLOCATE=false
B=benchmarks/randomisation_cost.py
EXPS=(serialfirst: oldunrolled:unrolled_first serialboth:serial_step nodraws:no_draws nodraws_nonoise:no_draws,no_first_noise,no_step_noise)
go() {  # name exp [ncu]
  local cmd="python3 $B --device gpu --envs CartPoleStayUp-v0 --n-envs 16384 --nepisodes 2 --repeats 1 --variants kernel-physics-only"
  if [ -n "$3" ]; then
    JAXROBO_KERNEL_EXPERIMENT="$2" /usr/local/cuda/bin/ncu --kernel-name regex:cartpole --launch-count 1 --section LaunchStats --section Occupancy $cmd > $OUT/x_$1.txt 2>&1
    echo "$1: $(grep -E 'Registers Per Thread' $OUT/x_$1.txt | awk '{print $NF}') regs; $(grep -E 'Theoretical Occupancy' $OUT/x_$1.txt | awk '{print $NF}') %"
  else
    JAXROBO_KERNEL_EXPERIMENT="$2" $cmd > $OUT/c_$1.txt 2>&1 || echo "$1 compile failed"
  fi
}
for e in "${EXPS[@]}"; do IFS=: read n x <<< "$e"; go $n "$x" & done
# the timed run compiles its own programs meanwhile (262144 envs)
unset XLA_PYTHON_CLIENT_PREALLOCATE
wait
echo compiled $(date)
for e in "${EXPS[@]}"; do IFS=: read n x <<< "$e"; go $n "$x" ncu; done
python3 $B --device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200 --repeats 3 --variants kernel-nominal,kernel-physics-only,kernel-randomised --out $OUT/time_serialfirst.json 2>&1 | grep -v Warning | tail -8
