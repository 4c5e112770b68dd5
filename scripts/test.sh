#!/usr/bin/env bash
# Install jaxrobo with its test extra (CPU JAX) and run the test suite. Used by the README and by CI.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -q -e ".[test]"
# No MUJOCO_GL here: `import jaxrobo` picks EGL or OSMesa where its library loads, else none (the rendering tests
# then skip with the reason, everything else runs). A MUJOCO_GL set by the caller is used where its library loads.
export JAX_PLATFORMS=cpu

# The suite runs on pytest-xdist workers: a test keeps about 1.2 cores busy (XLA compiles mostly on one thread),
# so two workers on 2 cores finish in about 0.6 of the serial time. One worker per core, at most 8 and at most one
# per 3 GiB of available memory: each holds its own JAX and compiles its own module fixtures, and beyond ~8 the
# longest test files bound the wall time anyway. JAXROBO_TEST_WORKERS=N sets the count (0 or 1: no workers).
# --dist loadfile keeps each test file on one worker, so a module-scoped fixture compiles once.
workers=${JAXROBO_TEST_WORKERS:-}
if [ -z "$workers" ]; then
  cores=$(nproc 2>/dev/null || echo 1)
  mem_gib=$(awk '/^MemAvailable:/ {print int($2 / 1048576)}' /proc/meminfo 2>/dev/null || echo 0)
  workers=$(( cores < 8 ? cores : 8 ))
  if [ "${mem_gib:-0}" -gt 0 ] && [ "$workers" -gt $(( mem_gib / 3 )) ]; then workers=$(( mem_gib / 3 )); fi
fi
xdist=()
if [ "$workers" -gt 1 ]; then xdist=(-n "$workers" --dist loadfile); fi
# Two tiers: by default the suite without the tests marked `slow` (long end-to-end runs and re-checks of what the
# default tier already covers in smaller form); --slow runs only those, --all everything. CI runs the first
# tier, then the second where its machine has the time (.ci/run).
tier=(-m "not slow")
args=()
for arg in "$@"; do
  case "$arg" in
    --slow) tier=(-m slow) ;;
    --all) tier=() ;;
    *) args+=("$arg") ;;
  esac
done
set -- ${args[@]+"${args[@]}"}
# The caller's own arguments come after ours, so that their -n or --dist wins; with --pdb/--trace (which need one
# process) or with xdist turned off (-p no:xdist) none are added.
for arg in "$@"; do
  case "$arg" in --pdb|--trace|no:xdist|-pno:xdist) xdist=() ;; esac
done
# Each xdist worker compiles into a cache folder of its own (tests/conftest.py says why). Before a session, while no
# worker writes, each folder takes the entries the others wrote in earlier sessions, so a program compiled once
# (the first tier, then the slow tier) is found whichever worker compiled it.
cache=${JAXROBO_TEST_CACHE:-.jax_cache/tests}
for d in "$cache"/gw*/; do
  for o in "$cache"/gw*/; do [ "$d" = "$o" ] || cp -rn "$o". "$d" 2>/dev/null || true; done
done
set +e
# --durations: the slowest tests in every log, where the suite's time goes (kept under ~20 min on 2 cores).
python -m pytest ${xdist[@]+"${xdist[@]}"} ${tier[@]+"${tier[@]}"} --durations=25 "$@"
rc=$?
set -e
# pytest exits 5 when it collected no test: treat that as a failure to notice, never as a pass.
if [ "$rc" = 5 ]; then echo "pytest collected no tests" >&2; exit 1; fi
exit "$rc"
