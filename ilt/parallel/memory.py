"""The memory this machine has free: what the solver choice and the simulator's size checks
compare their needs with."""

from __future__ import annotations

import os


def available_memory() -> int:
    """Bytes of memory the system has available now (Linux: MemAvailable), else all of it."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
