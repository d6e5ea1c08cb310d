"""Python's cyclic garbage collector in a process that runs for hours.

A full collection (generation 2) visits every container object the process tracks: after start-up the imported
modules alone (torch, NumPy, OpenCV, rclpy and ours) give hundreds of thousands, none of which will ever be
garbage. Full collections come whenever the objects that survived younger collections reach a quarter of those
already old, so during tracking each one held the thread that triggered it for about as long as several frames
take, and freed next to nothing (docs/benchmarks.md, issue 22). Freezing what exists once start-up is done
(``gc.freeze``) leaves the collector only what the run itself creates. Start-up goes on after the first frame:
the first keyframes compile the numba kernels and build the estimators, so what exists then is frozen once more.
"""
from __future__ import annotations

import gc
import threading

STARTUP_S = 30.0   # seconds after the first freeze at which what exists is frozen once more


def freeze_startup_objects(again_after_s: float | None = STARTUP_S) -> threading.Timer | None:
    """Collect the garbage start-up left, then move every object the collector tracks into its permanent
    generation, which later collections skip (reference counting still frees them; a reference cycle among them
    is never collected). Call once a process has imported its modules and built its long-lived objects, before
    its per-frame (per-message) work. With ``again_after_s``, the same happens once more that many seconds later
    on a daemon thread; the returned timer cancels it."""
    gc.collect()
    gc.freeze()
    if again_after_s is None:
        return None
    timer = threading.Timer(again_after_s, freeze_startup_objects, kwargs={"again_after_s": None})
    timer.daemon = True
    timer.start()
    return timer
