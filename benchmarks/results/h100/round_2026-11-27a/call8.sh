#!/usr/bin/env bash
# Writing the run directory on the GPU machine: the user's warm `jaxrobo train` (nominal cart-pole, the kernel,
# 65,536 envs x 200 episodes) with this tree and with the tree before write_once.patch, alternately, twice each.
set -u
R=$PWD; HERE=$R/benchmarks/results/h100/round_2026-11-27a
export JAXROBO_CACHE_DIR=/tmp/jc
rm -rf /tmp/p && mkdir /tmp/p && cp -r jaxrobo envs agents benchmarks pyproject.toml /tmp/p/ 2>/dev/null
(cd /tmp/p && git apply -R $HERE/write_once.patch) || { echo "reverse patch failed"; exit 1; }
ARGS="train --env CartPoleStayUp-v0 --set backend=analytic --n-envs 65536 --nepisodes 200 --no-progress --overwrite"
python3 -m jaxrobo.cli $ARGS --out /tmp/run_warmup > /dev/null 2>&1  # compiles into the cache
for round in 1 2; do
  for t in new before; do
    d=$R; [ $t = before ] && d=/tmp/p
    T0=$(date +%s.%N)
    (cd $d && PYTHONPATH=/tmp/site:$d python3 -m jaxrobo.cli $ARGS --out /tmp/run_$t > $OUT/write_${t}_$round.txt 2>&1)
    echo "$t round $round: rc=$? wall $(python3 -c "print(round($(date +%s.%N) - $T0, 1))") s | $(grep 'wall:' $OUT/write_${t}_$round.txt)"
  done
done
for f in episodes.csv episode_stats.csv records.npz qtables.npz eval.csv; do cmp -s /tmp/run_new/$f /tmp/run_before/$f && echo "$f identical" || echo "$f DIFFERS"; done
