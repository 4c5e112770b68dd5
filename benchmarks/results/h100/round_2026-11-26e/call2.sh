#!/usr/bin/env bash
# Where the registers are now (ncu's SASS page of the erfinv tree's randomised program), and two candidates that
# read reset-only parameters where a reset uses them: bounds_at_use.patch (the ranges' bounds) and
# reset_params_at_use.patch (those and the initial pose's): registers (ncu) and timings, beside the erfinv tree.
set -u
R=$PWD; HERE=$R/benchmarks/results/h100/round_2026-11-26e
export JAXROBO_CACHE_DIR=/tmp/jc
for t in A AC; do rm -rf /tmp/$t && mkdir /tmp/$t && cp -r jaxrobo envs agents benchmarks pyproject.toml /tmp/$t/; done
(cd /tmp/A && git apply $HERE/bounds_at_use.patch) && (cd /tmp/AC && git apply $HERE/reset_params_at_use.patch) \
  || { echo "patch failed"; exit 1; }
B=benchmarks/randomisation_cost.py
SMALL="--device gpu --envs CartPoleStayUp-v0 --n-envs 16384 --nepisodes 2 --repeats 1"
BIG="--device gpu --envs CartPoleStayUp-v0 --n-envs 262144 --nepisodes 200"
bg() {  # dir tag args...: a compile in the background
  local d=$1 tag=$2; shift 2
  (cd $d && XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=/tmp/site:$d python3 $B "$@" > $OUT/warm_$tag.txt 2>&1 \
     || echo "warm $tag failed") &
}
T0=$(date +%s)
bg $R E_small $SMALL --variants kernel-physics-only
bg $R E_big $BIG --repeats 1 --variants kernel-nominal,kernel-physics-only
bg /tmp/A A_small $SMALL --variants kernel-physics-only
bg /tmp/A A_big $BIG --repeats 1 --variants kernel-physics-only
bg /tmp/AC AC_small $SMALL --variants kernel-nominal,kernel-physics-only
bg /tmp/AC AC_big $BIG --repeats 1 --variants kernel-nominal,kernel-physics-only
wait; echo "compiled: $(( $(date +%s) - T0 )) s"
/usr/local/cuda/bin/ncu --kernel-name regex:cartpole --launch-count 1 --section SourceCounters --page source \
  --print-source sass --csv python3 $B $SMALL --variants kernel-physics-only 2>/dev/null | gzip > $OUT/sass_erfinv_physics-only.csv.gz
python3 benchmarks/results/h100/round_2026-11-26d/sass_summary.py $OUT/sass_erfinv_physics-only.csv.gz > $OUT/sass_summary.txt 2>&1
head -12 $OUT/sass_summary.txt
echo "sass: $(( $(date +%s) - T0 )) s"
for t in A AC; do
  v=kernel-physics-only; [ $t = AC ] && v=kernel-nominal,kernel-physics-only
  (cd /tmp/$t && PYTHONPATH=/tmp/site:/tmp/$t python3 benchmarks/kernel_occupancy.py --n-envs 16384 --nepisodes 2 \
     --variants $v --out $OUT/occupancy_$t.json 2>&1 | grep -v Warning | tail -3 | sed "s/^/$t: /")
done
echo "ncu: $(( $(date +%s) - T0 )) s"
for t in E A AC; do
  d=$R; [ $t != E ] && d=/tmp/$t
  echo "== $t"
  (cd $d && PYTHONPATH=/tmp/site:$d python3 $B $BIG --repeats 3 --variants kernel-nominal,kernel-physics-only,kernel-randomised \
     --out $OUT/times_$t.json 2>&1 | grep -v Warning | tail -5 | cut -c1-110)
done
echo "all: $(( $(date +%s) - T0 )) s"
