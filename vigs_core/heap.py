"""glibc malloc policies for processes whose large temporaries interleave with long-lived small state.

Process-wide policies, no-ops returning False where the C library is not glibc or another malloc was preloaded
(:func:`allocator`). Every process of ours takes :func:`single_arena`; then one of two opposite choices, each for
one kind of process:

* :func:`retain_freed_heap` for the Gaussian mapper, whose every step allocates and frees tens of megabytes:
  keeping them in the heap avoids a page fault per 4 KiB on the next step;
* :func:`map_large_blocks` for the loop-closure child, which handles one keyframe now and then: image-sized
  temporaries (flows, images read back) get their own mappings and go back to the kernel when freed, instead of
  leaving heap fragments between the small per-keyframe state kept for the whole run (RSS growth per keyframe
  in docs/benchmarks.md, issue 19).
"""
from __future__ import annotations

import ctypes
import resource
from pathlib import Path
from typing import Callable

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -2, -3, -8
_MALLOCS = ("jemalloc", "tcmalloc")   # mallocs that a process may preload instead of glibc's


def allocator(maps: str | None = None) -> str:
    """The malloc this process uses, from the libraries mapped into it (``maps``: the text of ``/proc/self/maps``,
    read when None): "jemalloc" or "tcmalloc" when one was preloaded (``LD_PRELOAD``), else "libc"; "unknown"
    without ``/proc``. A long run's RSS growth depends on it (docs/benchmarks.md, issue 19), so the report says
    which."""
    if maps is None:
        try:
            maps = Path("/proc/self/maps").read_text()
        except OSError:
            return "unknown"
    for name in _MALLOCS:
        if f"/lib{name}" in maps:
            return name
    return "libc"


def peak_rss_mb(status: str | None = None) -> float:
    """Peak resident memory of this process, MiB: ``VmHWM`` of ``status`` (the text of ``/proc/self/status``, read
    when None), ``ru_maxrss`` without ``/proc``. Not ``ru_maxrss`` where ``/proc`` is there: Linux carries it
    across ``exec``, so a spawned worker's would start at what the caller held when it forked the worker. Each
    worker child reports its own: the caller's ``RUSAGE_CHILDREN`` covers only children already ended, and only
    the largest of them."""
    if status is None:
        try:
            status = Path("/proc/self/status").read_text()
        except OSError:
            status = ""
    hwm = [line.split()[1] for line in status.splitlines() if line.startswith("VmHWM:")]
    return int(hwm[0]) / 1024.0 if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def worker_preload(preload: str) -> str:
    """``LD_PRELOAD`` for a worker child: ``preload`` without jemalloc or tcmalloc. The workers keep glibc's malloc
    and their own policies here (the mapper's retained heap, the loop-closure child's fixed mmap threshold): a
    preloaded jemalloc cost the mapper page faults (docs/benchmarks.md, issue 19), while it lowers the tracking
    process's heap growth. Other preloaded libraries stay."""
    kept = [p for p in preload.replace(":", " ").split()
            if not any(Path(p).name.startswith(f"lib{name}") for name in _MALLOCS)]
    return " ".join(kept)


def _mallopt() -> Callable[[int, int], int] | None:
    if allocator() not in ("libc", "unknown"):   # glibc's mallopt would succeed without effect
        return None
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return None
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return mallopt


def single_arena() -> bool:
    """Serve every thread of this process from glibc's main heap (``M_ARENA_MAX`` 1; the ``MALLOC_ARENA_MAX=1``
    of the environment, set from inside). By default each new thread that allocates gets a heap of its own (up to
    eight per core), and each keeps its own fragments between the blocks that live for the whole run: on the
    procedural soak that made the tracking process and the mapper child grow about twice as fast per keyframe
    (docs/benchmarks.md, issue 19). Our threads (frame reader, senders, the mapper's worker, executors) allocate
    little concurrently, so sharing one heap's lock costs little. Call it before the process starts threads:
    a thread that has allocated keeps its heap."""
    mallopt = _mallopt()
    return mallopt is not None and mallopt(_M_ARENA_MAX, 1) == 1


def retain_freed_heap() -> bool:
    """Make glibc's malloc keep freed memory for reuse instead of handing it back to the kernel.

    Every optimisation step allocates and frees tens of megabytes of CPU tensors (PyTorch's CPU allocator
    calls malloc directly). With glibc's defaults, blocks above the mmap threshold are mapped and unmapped
    per allocation and the top of the heap is trimmed once more than the trim threshold is free, so the
    next step takes a page fault (and the kernel zeroes a page) for every 4 KiB again: in the mapping
    benchmark that was about 10% of the CPU time, all of it system time. Serving blocks up to 32 MiB (the
    largest mmap threshold glibc accepts on 64-bit) from the heap, trimming only beyond 1 GiB free and
    growing the heap 64 MiB at a time keeps the pages mapped: the process retains its peak heap size."""
    mallopt = _mallopt()
    if mallopt is None:
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, 32 << 20) == 1
    ok &= mallopt(_M_TRIM_THRESHOLD, 1 << 30) == 1
    ok &= mallopt(_M_TOP_PAD, 64 << 20) == 1
    return bool(ok)


def map_large_blocks(threshold: int = 128 << 10) -> bool:
    """Serve blocks of ``threshold`` bytes and more from their own mappings, always (a fixed threshold: glibc's
    default raises it to the largest block freed so far, after which image-sized blocks come from the heap)."""
    mallopt = _mallopt()
    return mallopt is not None and mallopt(_M_MMAP_THRESHOLD, threshold) == 1
