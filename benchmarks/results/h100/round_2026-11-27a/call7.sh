#!/usr/bin/env bash
# The user's command, wall time included: `jaxrobo train` of the analytic cart-pole on one GPU (the kernel), nominal
# and with its masses and pole length randomised, each first with an empty compile cache of its own, then again
# with that cache filled.
set -u
ARGS="train --env CartPoleStayUp-v0 --set backend=analytic --n-envs 65536 --nepisodes 200 --no-progress --overwrite"
RAND='--set randomise=true --set rand_cart_mass=[0.8,1.2] --set rand_pole_mass=[0.8,1.2] --set rand_pole_length=[0.9,1.1]'
for cache in cold warm; do
  for v in nominal randomised; do
    extra=""; [ $v = randomised ] && extra=$RAND
    echo "== $v, $cache cache"
    T0=$(date +%s.%N)
    JAXROBO_CACHE_DIR=/tmp/jc_$v python3 -m jaxrobo.cli $ARGS $extra --out /tmp/run_$v > $OUT/train_${v}_$cache.txt 2>&1
    rc=$?
    echo "rc=$rc wall $(python3 -c "print(round($(date +%s.%N) - $T0, 1))") s"
    grep -v Warning $OUT/train_${v}_$cache.txt | grep -i "plan\|compile\|steps/s\|episode\|took\|s)" | head -8 | cut -c1-160
  done
done
