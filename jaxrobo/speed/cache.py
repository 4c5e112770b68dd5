"""The persistent JAX compilation cache, on by default, so a second run of the same configuration skips XLA.

Compiling the training loop of an MJX env takes tens of seconds on a CPU; the compiled executable only depends
on the program and the device, so it is written to disk and reused by every later process. The directory is
``$JAXROBO_CACHE_DIR`` if set, else ``~/.cache/jaxrobo/jax``; ``JAXROBO_CACHE_DIR=off`` (or ``0``, ``none``,
``false``, empty) turns it off. Call :func:`enable_compilation_cache` before the first compile of a process.

JAX keys each entry on the lowered module itself (with the JAX version, the backend and the compile options),
so the cache can never run code other than what the process has just traced: a physics step patched at run
time, or another execution plan (:class:`jaxrobo.speed.plan.ExecutionPlan`), lowers to another module and compiles
afresh. A second start therefore still traces its programs, which on a GPU host took most of a warm compile
(seconds for an MJX step); :mod:`jaxrobo.speed.reuse` keeps the traces too, in ``traced/`` under this directory,
keyed on everything a trace reads, a function patched in at run time included (a plan's ``reuse_traces``).
"""
from __future__ import annotations

import os
import sys
import tempfile

import jax

ENV_VAR = "JAXROBO_CACHE_DIR"
DEFAULT_DIR = os.path.join("~", ".cache", "jaxrobo", "jax")
_OFF = {"off", "0", "none", "false", "no", "disable", "disabled", ""}


def cache_dir(path: str | None = None) -> str | None:
    """The directory to use: ``path`` if given, else ``$JAXROBO_CACHE_DIR``, else the default; None when off."""
    value = path if path is not None else os.environ.get(ENV_VAR, DEFAULT_DIR)
    if value.strip().lower() in _OFF:
        return None
    return os.path.abspath(os.path.expanduser(value))


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Turn the persistent compilation cache on (every compile is cached, however small or quick).

    Returns the directory in use, or None when the cache is turned off (``path`` or ``$JAXROBO_CACHE_DIR`` set
    to ``off``). Raises ``OSError`` naming the directory if it cannot be created or written (a file, a read-only
    or full file system, a path under a file): :func:`enable_or_warn` turns that into a warning.
    """
    directory = cache_dir(path)
    if directory is None:
        return None
    try:
        os.makedirs(directory, exist_ok=True)
        # Writable? (os.access says yes to root on a read-only file system.) A probe file, removed at once.
        fd, probe = tempfile.mkstemp(prefix=".probe.", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise OSError(f"{ENV_VAR}={directory!r}: cannot use it as the compilation cache directory "
                      f"({err.strerror or err})") from None
    jax.config.update("jax_compilation_cache_dir", directory)
    # JAX only caches compiles slower than 1 s and entries above a filesystem-dependent size by default; our
    # start-up is the sum of many small compiles (init, progress statistics, evaluation), so cache them all.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    _reset_if_initialised()
    return directory


def enable_or_warn(prog: str = "jaxrobo") -> str | None:
    """:func:`enable_compilation_cache` for a command line: an unusable directory is one warning line on stderr
    and the cache off (every compile then runs afresh), never an error."""
    try:
        return enable_compilation_cache()
    except OSError as err:
        print(f"{prog}: warning: {err}; the compilation cache is off for this run", file=sys.stderr)
        return None


def entries(directory: str | None) -> int:
    """Number of files in a cache directory (a compile that adds none was served from the cache)."""
    if not directory or not os.path.isdir(directory):
        return 0
    return sum(len(files) for _, _, files in os.walk(directory))


def _reset_if_initialised() -> None:
    """JAX opens the cache at its first compile; if that already happened, make it reopen at the new path."""
    try:
        from jax._src import compilation_cache as cc

        if getattr(cc, "_cache_initialized", False):
            cc.reset_cache()
    except Exception:  # noqa: BLE001 - private API; without it the cache simply applies from the next process
        pass
