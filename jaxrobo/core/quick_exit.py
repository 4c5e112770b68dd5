"""The ``jaxrobo`` command's exit without the interpreter's teardown.

A command's work is on disk (published and flushed) when its ``main`` returns. What Python does after that, freeing
every module's objects and the JAX backend's device client one destructor at a time, kept nothing and cost a
default command 0.3-0.6 s of its wall on an H200 (``benchmarks/results/h200/quick_exit.json``) and 0.2 s on 2 CPU
cores. :func:`exit_process` does what Python's shutdown does that can matter, in its order (waits for the
threads that are not daemons, runs every ``atexit`` handler: JAX's, logging's, a caller's), flushes the standard
streams and ends the process with ``os._exit``; the operating system frees the memory and the device.

It reaches into CPython's private ``atexit._run_exitfuncs`` (present in every CPython 3), so it is guarded: another
interpreter, a missing function, or a process being traced or profiled (coverage's tracer and cProfile write
their results in the teardown it skips) takes Python's own exit instead. Only the command's own process calls it
(``jaxrobo.cli.entry``); ``jaxrobo.cli.main`` returns to a caller as any function does.
"""
from __future__ import annotations

import atexit
import os
import sys
import threading

#: The CPython versions whose ``atexit._run_exitfuncs`` runs every handler, last registered first, and clears them
#: (the running one is checked by ``tests/test_quick_exit.py``); outside them the exit is Python's own.
CHECKED = ((3, 10), (3, 14))


def available() -> bool:
    """Whether :func:`exit_process` may skip the teardown in this interpreter and this process, now."""
    return (sys.implementation.name == "cpython" and CHECKED[0] <= sys.version_info[:2] <= CHECKED[1]
            and callable(getattr(atexit, "_run_exitfuncs", None))
            and sys.gettrace() is None and sys.getprofile() is None)


def exit_process(code: int) -> None:
    """End the process with ``code``: Python's own exit (``sys.exit``) where :func:`available` says no, else the
    threads joined, the ``atexit`` handlers run, the streams flushed and ``os._exit``."""
    if not available():
        sys.exit(code)
    for thread in threading.enumerate():  # Python's shutdown waits for these first, and so does this
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()  # a handler's exception is printed, not raised, as at a normal exit
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: Python's exit would lose the same bytes
            pass
    os._exit(code)
