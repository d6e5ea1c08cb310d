"""Start-up objects frozen out of Python's full collections (vigs_core.gc_freeze): what exists at the call, and
again a given time later, is no longer visited by the collector, while cycles made afterwards are still
collected."""
import gc
import time
import weakref

from vigs_core.gc_freeze import freeze_startup_objects


class _Node:
    pass


def _cycle() -> _Node:
    node = _Node()
    node.me = node
    return node


def _tracked(obj) -> bool:
    return any(o is obj for o in gc.get_objects())


def test_start_up_objects_are_left_out_of_collections_and_later_cycles_are_still_collected():
    startup = _cycle()   # alive when the process starts its work
    try:
        freeze_startup_objects(again_after_s=0.3)
        frozen = gc.get_freeze_count()
        assert frozen > 1000   # this process's modules, at least
        assert not _tracked(startup)
        warmup = _cycle()   # made during the start-up's rest (first keyframes, compiled kernels)
        later = _cycle()
        ref = weakref.ref(later)
        del later
        gc.collect()
        assert ref() is None and _tracked(warmup)   # collected as before the freeze
        deadline = time.monotonic() + 10.0
        while _tracked(warmup) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _tracked(warmup) and gc.get_freeze_count() > frozen   # frozen by the second, later freeze
    finally:
        gc.unfreeze()


def test_the_second_freeze_can_be_cancelled():
    try:
        timer = freeze_startup_objects(again_after_s=0.2)
        timer.cancel()
        made = _cycle()
        time.sleep(0.4)
        assert _tracked(made)
        assert freeze_startup_objects(again_after_s=None) is None
    finally:
        gc.unfreeze()
