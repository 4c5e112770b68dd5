#!/usr/bin/env bash
# Run a command on this machine as if it had no OpenGL library: `bash scripts/without_gl.sh CMD [ARGS...]`.
#
# The command runs in a private mount namespace (`unshare`; a user namespace too when not root) in which every
# libEGL*, libGL* (GLX, GLES, GLU, glvnd), libglapi* and libOSMesa* shared library the dynamic loader could
# find is bind-masked by an empty file, so loading any of them fails. Nothing on the machine changes: the
# masks exist only inside the namespace and vanish with it. Before the command runs, the script checks that
# none of libEGL, libGL, libOpenGL, libGLESv2, libGLESv1_CM, libOSMesa loads (the names and suffixes PyOpenGL
# tries), and fails (exit 1) if one still does.
#
# `--check` instead of a command: only set up and verify the masks.
# Exit 3, with the reason on stderr, when the mechanism is not available here (no `unshare`, or namespaces
# are not permitted, as in some containers): callers skip their no-GL step then.
set -euo pipefail

if [ "${1:-}" = "" ]; then
  echo "usage: bash scripts/without_gl.sh CMD [ARGS...] | --check" >&2
  exit 2
fi

if [ "${_JAXROBO_WITHOUT_GL:-}" != inside ]; then
  if ! command -v unshare >/dev/null; then
    echo "without_gl: unavailable: no unshare command (util-linux)" >&2
    exit 3
  fi
  # A mount namespace needs CAP_SYS_ADMIN: root has it (CI), others (and root in a container without it) get
  # it inside a user namespace of their own, where that is permitted.
  why=""
  for ns in "--mount" "--user --map-root-user --mount"; do
    read -r -a flags <<< "$ns"
    if probe=$(unshare "${flags[@]}" --propagation private sh -c 'mount --bind /dev/null /dev/null' 2>&1); then
      export _JAXROBO_WITHOUT_GL=inside
      # In a user namespace the command runs as "root": give it its own temporary directory, so that tools
      # keyed by user name (pytest's /tmp/pytest-of-root) do not collide with the real root's.
      [ "${flags[0]}" = --user ] && [ -z "${TMPDIR:-}" ] && TMPDIR=$(mktemp -d) && export TMPDIR
      exec unshare "${flags[@]}" --propagation private -- bash "$0" "$@"
    fi
    why="${why:+$why; }unshare $ns: ${probe:-failed}"
  done
  echo "without_gl: unavailable: cannot create a mount namespace with bind mounts here ($why)" >&2
  exit 3
fi

# Inside the namespace: find the GL libraries the loader could reach, and mask each real file once.
dirs=(/lib /lib64 /usr/lib /usr/lib64 /usr/local/lib /lib/x86_64-linux-gnu /usr/lib/x86_64-linux-gnu
      /lib/aarch64-linux-gnu /usr/lib/aarch64-linux-gnu /usr/local/lib/x86_64-linux-gnu)
IFS=: read -r -a ld_dirs <<< "${LD_LIBRARY_PATH:-}"
dirs+=("${ld_dirs[@]}")
while read -r dir; do dirs+=("$dir"); done < <(ldconfig -p 2>/dev/null \
    | awk -F'=> ' 'NF == 2 {sub(/\/[^\/]*$/, "", $2); print $2}' | sort -u)
for conf in /etc/ld.so.conf /etc/ld.so.conf.d/*.conf; do
  [ -r "$conf" ] && while read -r line; do [[ "$line" = /* ]] && dirs+=("$line"); done < "$conf"
done
prefix=$(python3 -c 'import sys; print(sys.prefix)' 2>/dev/null || true)

empty=$(mktemp)
declare -A masked=()
mask() {
  local real
  real=$(realpath -e "$1" 2>/dev/null) || return 0
  [ -f "$real" ] && [ -z "${masked[$real]:-}" ] || return 0
  mount --bind "$empty" "$real"
  masked[$real]=1
}
shopt -s nullglob
declare -A seen=()
for dir in "${dirs[@]}"; do
  [ -n "$dir" ] && [ -d "$dir" ] || continue
  dir=$(realpath "$dir")
  [ -z "${seen[$dir]:-}" ] || continue
  seen[$dir]=1
  for lib in "$dir"/libEGL*.so* "$dir"/libGL*.so* "$dir"/libglapi*.so* "$dir"/libOSMesa*.so*; do mask "$lib"; done
done
if [ -n "$prefix" ] && [ -d "$prefix" ]; then  # libraries bundled by Python packages
  while read -r lib; do mask "$lib"; done < <(find "$prefix" \( -name 'libEGL*.so*' -o -name 'libGL*.so*' \
      -o -name 'libglapi*.so*' -o -name 'libOSMesa*.so*' \) 2>/dev/null)
fi

python3 - <<'EOF'
import ctypes, sys
loaded = []
for name in ("EGL", "GL", "OpenGL", "GLESv2", "GLESv1_CM", "OSMesa"):
    for filename in [f"lib{name}.so"] + [f"lib{name}.so.{i}" for i in range(10)]:
        try:
            ctypes.CDLL(filename)
        except OSError:
            continue
        loaded.append(filename)
if loaded:
    sys.exit(f"without_gl: still loadable: {', '.join(loaded)}")
EOF
echo "without_gl: ${#masked[@]} GL library files masked; libEGL, libGL, libOpenGL, libGLES*, libOSMesa do not load" >&2

if [ "$1" = --check ]; then exit 0; fi
unset _JAXROBO_WITHOUT_GL
exec "$@"
