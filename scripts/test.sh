#!/usr/bin/env bash
# Install jaxrobo with its test extra (CPU JAX) and run the test suite. Used by the README and by CI.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -q -e ".[test]"
# No MUJOCO_GL here: `import jaxrobo` picks EGL or OSMesa where its library loads, else none (the rendering tests
# then skip with the reason, everything else runs). A MUJOCO_GL set by the caller is used where its library loads.
export JAX_PLATFORMS=cpu
set +e
python -m pytest "$@"
rc=$?
set -e
# pytest exits 5 when it collected no test: treat that as a failure to notice, never as a pass.
if [ "$rc" = 5 ]; then echo "pytest collected no tests" >&2; exit 1; fi
exit "$rc"
