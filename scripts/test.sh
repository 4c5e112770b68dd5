#!/usr/bin/env bash
# Install jaxrobo with its test extra (CPU JAX) and run the test suite. Used by the README and by CI.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -q -e ".[test]"
export JAX_PLATFORMS=cpu MUJOCO_GL="${MUJOCO_GL:-osmesa}" PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
set +e
python -m pytest "$@"
rc=$?
set -e
# pytest exits 5 when it collected no test: treat that as a failure to notice, never as a pass.
if [ "$rc" = 5 ]; then echo "pytest collected no tests" >&2; exit 1; fi
exit "$rc"
