#!/usr/bin/env bash
# Is the pinned row's extra cost the order of the timings? Every variant compiled in parallel, then timed in two
# processes, in rounds (randomisation_cost.py now times every variant once per round), in opposite orders, with
# the card's clock, power and temperature logged every 200 ms.
set -u
export JAXROBO_CACHE_DIR=/tmp/jc
B=benchmarks/randomisation_cost.py
BIG="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
T0=$(date +%s)
for v in kernel-nominal kernel-physics-only kernel-pinned kernel-randomised; do
  (XLA_PYTHON_CLIENT_PREALLOCATE=false python3 $B $BIG --repeats 1 --variants $v > $OUT/warm_$v.txt 2>&1 || echo "warm $v failed") &
done
wait; echo "compile: $(( $(date +%s) - T0 )) s"
nvidia-smi --query-gpu=timestamp,clocks.sm,clocks.mem,power.draw,temperature.gpu,clocks_throttle_reasons.active \
  --format=csv -lms 200 > $OUT/smi.csv 2>&1 &
SMI=$!
echo "== forward"
python3 $B $BIG --repeats 5 --variants kernel-nominal,kernel-physics-only,kernel-pinned,kernel-randomised \
  --out $OUT/times_forward.json 2>&1 | grep -v Warning | tail -7 | cut -c1-120
echo "== reverse"
python3 $B $BIG --repeats 5 --variants kernel-randomised,kernel-pinned,kernel-physics-only,kernel-nominal \
  --out $OUT/times_reverse.json 2>&1 | grep -v Warning | tail -7 | cut -c1-120
kill $SMI
echo "all: $(( $(date +%s) - T0 )) s"
