"""The start-up part of a command's wall (imports, device discovery, configuration: everything before the first
compile). In the ``jaxrobo`` command's own process it counts from the process's start, which a timer started inside
Python cannot see; where a caller runs the command in its own process (``jaxrobo.cli.main([...])`` from a test, a
notebook or a script) it counts from the call, not from the caller's start."""
from __future__ import annotations

import os
import time

_entered: float | None = None


def command_entered() -> None:
    """Mark the start of one command (``jaxrobo.cli.main``)."""
    global _entered
    _entered = time.perf_counter()


def command_seconds() -> float | None:
    """Seconds of this command so far (read before the first compile: its start-up; at the end: its wall): since
    the process started when this process is the ``jaxrobo`` command, else since :func:`command_entered` (None
    where neither is known)."""
    from jaxrobo.core.environ import running_cli

    if running_cli():
        return process_seconds()
    return None if _entered is None else time.perf_counter() - _entered


def process_seconds() -> float | None:
    """Seconds since the process started, from the kernel's record of it (Linux ``/proc``; 10 ms resolution), or
    None where there is none to read."""
    try:
        with open("/proc/self/stat", "rb") as f:
            stat = f.read().decode("ascii", "replace")
        with open("/proc/uptime", "rb") as f:
            uptime = float(f.read().split()[0])
        # Field 22 (starttime, clock ticks after boot) counts from the last ')' (the command name may hold spaces).
        start_ticks = int(stat.rsplit(")", 1)[1].split()[19])
        return max(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 0.0)
    except (OSError, ValueError, IndexError):
        return None
