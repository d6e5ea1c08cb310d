"""The name a child process shows to ``ps``, ``top`` and ``/proc/PID/comm``: multiprocessing's spawned children
all run the same command line, so tools (and ``vigs bench soak``) could not tell the loop-closure worker from
the mapper."""
from __future__ import annotations

import ctypes
import ctypes.util

_PR_SET_NAME = 15   # prctl(2)


def set_process_name(name: str) -> bool:
    """Set this process's name (Linux: at most 15 bytes are kept); False where prctl is not available."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        return libc.prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False
