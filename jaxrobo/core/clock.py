"""Seconds since this process started, for the start-up part of a command's wall (imports, device discovery,
configuration: everything before the first compile), which a timer started inside Python cannot see."""
from __future__ import annotations

import os


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
