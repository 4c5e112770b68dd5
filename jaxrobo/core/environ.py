"""Every environment variable jaxrobo reads or depends on, checked in one place, at the boundary, with a message
that names it: ``jaxrobo``'s own (:data:`JAXROBO_VARIABLES`) and the third-party ones whose bad values would
otherwise surface as a traceback or a native crash deep inside a run (``MUJOCO_GL``, ``JAX_ENABLE_X64``,
``JAX_PLATFORMS``).

Two moments: :func:`check_before_import`, from ``jaxrobo/__init__.py``, before JAX and MuJoCo are imported (both
read their variables at import and fail there); :func:`check`, from the CLI's ``main`` before a command runs,
for what needs JAX (``JAX_PLATFORMS``) or concerns jaxrobo's own variables. This module imports no JAX at
module level.
"""
from __future__ import annotations

import math
import os
import sys
from typing import Any, Sequence

#: jaxrobo's own variables: what each may hold (docs/scaling.md for the multi-host ones).
JAXROBO_VARIABLES = {
    "JAXROBO_CACHE_DIR": "the compilation cache directory, or off (jaxrobo.speed.cache)",
    "JAXROBO_REUSE_TRACES": "on (the default) or off: read traced programs back (jaxrobo.speed.reuse)",
    "JAXROBO_COORDINATOR": "host:port of process 0 of a multi-host run",
    "JAXROBO_NUM_PROCESSES": "processes of a multi-host run, an integer >= 1",
    "JAXROBO_PROCESS_ID": "this process's index, 0 .. JAXROBO_NUM_PROCESSES - 1",
    "JAXROBO_DISTRIBUTED": "'auto' (JAX's own cluster detection) or unset",
    "JAXROBO_INIT_TIMEOUT": "seconds to wait for every process to join, an integer >= 1",
    "JAXROBO_PAUSE_BEFORE_PUBLISH": "seconds to wait before publishing a run (fault tests), a number >= 0",
}
#: Bounds of the integer and number variables (seconds or counts a C++ int must hold).
_INT_MAX = 2**31 - 1
PAUSE_MAX = 3600.0

#: ``JAX_ENABLE_X64``'s accepted spellings (JAX's own ``bool_env``); anything else fails ``import jax``.
_TRUTH = ("y", "yes", "t", "true", "on", "1", "n", "no", "f", "false", "off", "0", "")
#: ``MUJOCO_GL``'s values ``import mujoco`` accepts on Linux (anything else fails the import).
_MUJOCO_GL = ("disable", "disabled", "off", "false", "0", "enable", "enabled", "on", "true", "1", "glfw", "",
              "glx", "egl", "osmesa")


def problems_before_import() -> list[str]:
    """What ``import jax`` / ``import mujoco`` would fail on, one line each (empty when nothing)."""
    out = []
    x64 = os.environ.get("JAX_ENABLE_X64")
    if x64 is not None and x64.strip().lower() not in _TRUTH:
        out.append(f"JAX_ENABLE_X64={x64!r}: not a truth value; unset it (jaxrobo runs in 32-bit: 0, false, off)")
    gl = os.environ.get("MUJOCO_GL")
    if gl is not None and sys.platform.startswith("linux") and gl.strip().lower() not in _MUJOCO_GL:
        out.append(f"MUJOCO_GL={gl!r}: not a rendering backend; use egl, osmesa, glfw, glx or disable (or unset it)")
    return out


def running_cli() -> bool:
    """Whether this process is the ``jaxrobo`` command (its console script or ``python -m jaxrobo.cli``)."""
    argv = getattr(sys, "orig_argv", sys.argv)
    if os.path.basename(sys.argv[0] if sys.argv else "") == "jaxrobo":
        return True
    return any(a == "-m" and b in ("jaxrobo.cli", "jaxrobo") for a, b in zip(argv, argv[1:]))


def check_before_import() -> None:
    """Refuse the variables JAX and MuJoCo read at import (:func:`problems_before_import`): the ``jaxrobo``
    command prints one line and exits 2 (its ``main`` is not reached: the import comes first); a library import
    raises ``ValueError`` naming the variable, not the dependency's traceback."""
    problems = problems_before_import()
    if not problems:
        return
    if running_cli():
        print(f"jaxrobo: {problems[0]}", file=sys.stderr)
        raise SystemExit(2)
    raise ValueError(problems[0])


def env_int(name: str, low: int, high: int = _INT_MAX, default: int | None = None) -> int | None:
    """The integer environment variable ``name`` in ``low..high`` (``default`` when unset or empty); a
    :class:`~jaxrobo.core.config.ConfigError` naming it otherwise."""
    from jaxrobo.core.config import ConfigError

    text = os.environ.get(name)
    if text is None or not text.strip():
        return default
    try:
        value = int(text.strip())
    except ValueError:
        raise ConfigError(f"{name}={text!r}: expected an integer >= {low} and <= {high}") from None
    if not low <= value <= high:
        raise ConfigError(f"{name}={value}: expected an integer >= {low} and <= {high}")
    return value


def env_seconds(name: str, high: float) -> float | None:
    """A number of seconds in ``[0, high]`` from the variable ``name`` (None when unset or empty)."""
    from jaxrobo.core.config import ConfigError

    text = os.environ.get(name)
    if text is None or not text.strip():
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value <= high:  # NaN fails too
        raise ConfigError(f"{name}={text!r}: expected a number of seconds in 0..{high:g}")
    return value


#: An on/off variable's spellings.
_ON, _OFF = ("1", "on", "true", "yes"), ("0", "off", "false", "no")


def switch(name: str, default: bool = True) -> bool:
    """The on/off variable ``name`` (``default`` when unset or empty); a ConfigError naming it otherwise."""
    from jaxrobo.core.config import ConfigError

    text = os.environ.get(name, "").strip().lower()
    if not text:
        return default
    if text not in _ON + _OFF:
        raise ConfigError(f"{name}={os.environ[name]!r}: expected on or off ({', '.join(_ON + _OFF)})")
    return text in _ON


def check_jaxrobo_variables() -> None:
    """jaxrobo's own variables (:data:`JAXROBO_VARIABLES`), each parsed as its reader will; ConfigError naming
    the first bad one."""
    from jaxrobo.core.config import ConfigError

    mode = os.environ.get("JAXROBO_DISTRIBUTED")
    if mode is not None and mode.strip().lower() not in ("", "auto"):
        raise ConfigError(f"JAXROBO_DISTRIBUTED={mode!r}: expected 'auto' (JAX's own cluster detection) or unset")
    n = env_int("JAXROBO_NUM_PROCESSES", 1)
    pid = env_int("JAXROBO_PROCESS_ID", 0)
    if n is not None and pid is not None and pid >= n:
        raise ConfigError(f"JAXROBO_PROCESS_ID={pid}: must be in 0..{n - 1} (JAXROBO_NUM_PROCESSES={n})")
    env_int("JAXROBO_INIT_TIMEOUT", 1)
    switch("JAXROBO_REUSE_TRACES")
    env_seconds("JAXROBO_PAUSE_BEFORE_PUBLISH", PAUSE_MAX)
    coordinator = os.environ.get("JAXROBO_COORDINATOR")
    if coordinator:
        try:
            check_coordinator(coordinator)
        except ValueError as err:
            raise ConfigError(str(err)) from None
        if pid == 0:
            _check_port_free(coordinator)


def check_coordinator(address: str) -> None:
    """``host:port`` whose host resolves (``socket.getaddrinfo``) and whose port is a number in 1..65535:
    otherwise a ValueError naming ``JAXROBO_COORDINATOR`` now, instead of a silent wait for a coordinator that
    cannot be reached."""
    import socket

    host, sep, port = address.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"JAXROBO_COORDINATOR={address!r}: expected host:port (port 1..65535)")
    try:
        socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError, OSError) as err:
        raise ValueError(f"JAXROBO_COORDINATOR={address!r}: the host {host!r} does not resolve ({err})") from None


def _check_port_free(coordinator: str) -> None:
    """Process 0 serves the coordinator at its port: one already taken would crash JAX's service natively."""
    import errno
    import socket

    from jaxrobo.core.config import ConfigError

    port = int(coordinator.rpartition(":")[2])
    for family, anywhere in ((socket.AF_INET, ""), (socket.AF_INET6, "::")):
        try:
            s = socket.socket(family, socket.SOCK_STREAM)
        except OSError:  # no IPv6 on this host
            continue
        with s:
            # As a server binds: a port whose last connection is in TIME_WAIT (a run that just ended) is free.
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((anywhere, port))
            except OSError as err:
                if err.errno == errno.EADDRINUSE:
                    raise ConfigError(f"JAXROBO_COORDINATOR={coordinator!r}: port {port} is already in use on this "
                                      "host (process 0 serves the coordinator there); choose a free port") from None


def check_platforms() -> None:
    """``JAX_PLATFORMS`` naming a platform this machine lacks (``tpu`` without libtpu): a ConfigError naming it,
    instead of JAX's RuntimeError at the first array."""
    value = os.environ.get("JAX_PLATFORMS")
    if not value or not value.strip():
        return
    import jax

    from jaxrobo.core.config import ConfigError

    try:
        jax.devices()
    except RuntimeError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        first = first.split(" (set JAX_PLATFORMS")[0]  # JAX's own hint; the message below gives the way out
        raise ConfigError(f"JAX_PLATFORMS={value!r}: a platform it names is not available here ({first}); "
                          "unset it or name one this machine has (cpu, cuda, ...)") from None


def check(light: bool = False) -> None:
    """Everything above that :func:`check_before_import` did not cover: jaxrobo's own variables, and (unless
    ``light``: a command that never touches a device) ``JAX_PLATFORMS``. ConfigError naming the variable."""
    check_jaxrobo_variables()
    # A multi-host run joins jax.distributed before any backend starts: the platforms are JAX's to check there.
    distributed = os.environ.get("JAXROBO_COORDINATOR") or os.environ.get("JAXROBO_DISTRIBUTED", "").strip()
    if not light and not distributed:
        check_platforms()


def usable_cores() -> int:
    """The CPU cores this process may run on: its affinity where the system reports one (a container's or
    ``taskset``'s share), else ``os.cpu_count()``."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def in_threads(fn: Any, starts: Sequence[int], ends: Sequence[int], *, threads: int | None = None,
               name: str = "jaxrobo-blocks") -> list:
    """``[fn(a, b) for a, b in zip(starts, ends)]``, in order, the blocks run by up to ``threads`` threads (default:
    a thread per usable core; one block or one thread: in the caller). For numpy work on independent blocks of a
    large array, whose sorts, reductions and copies release Python's lock: a block's result is the same whichever
    thread computes it."""
    threads = usable_cores() if threads is None else max(int(threads), 1)
    workers = min(len(starts), threads)
    if workers <= 1:
        return [fn(a, b) for a, b in zip(starts, ends)]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(workers, thread_name_prefix=name) as pool:
        return list(pool.map(fn, starts, ends))
