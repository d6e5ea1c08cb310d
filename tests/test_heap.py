"""Which malloc a process uses, from its mapped libraries: the report records it, the glibc policies of
:mod:`vigs_core.heap` do nothing under another one, and worker children do not inherit a preloaded one."""
import ctypes.util
import os
import subprocess
import sys

from vigs_core import heap
from vigs_core.child_process import ChildChannel, enter_child, send
from vigs_core.heap import allocator, worker_preload

MAPS = """7f0000000000-7f0000001000 r-xp 00000000 08:01 1 /usr/lib/x86_64-linux-gnu/libc.so.6
7f0000002000-7f0000003000 r-xp 00000000 08:01 2 /usr/lib/python3.12/lib-dynload/_ctypes.so
"""


def test_allocator_names_a_preloaded_malloc_and_otherwise_libc():
    assert allocator(MAPS) == "libc"
    assert allocator(MAPS + "7f1-7f2 r-xp 0 08:01 3 /usr/lib/x86_64-linux-gnu/libjemalloc.so.2\n") == "jemalloc"
    assert allocator(MAPS + "7f1-7f2 r-xp 0 08:01 3 /usr/lib/libtcmalloc_minimal.so.4.5.10\n") == "tcmalloc"
    assert allocator("7f1-7f2 r-xp 0 08:01 3 /home/me/jemalloc_notes/libc.so.6\n") == "libc"


def test_this_process():
    assert allocator() == ("jemalloc" if "jemalloc" in os.environ.get("LD_PRELOAD", "") else "libc")


def test_under_another_malloc_the_glibc_policies_are_not_set(monkeypatch):
    monkeypatch.setattr(heap, "allocator", lambda maps=None: "jemalloc")   # as where one is preloaded
    assert heap.map_large_blocks() is False and heap.retain_freed_heap() is False


def test_worker_preload_drops_only_a_preloaded_malloc():
    assert worker_preload("libjemalloc.so.2") == ""
    assert worker_preload("/usr/lib/x86_64-linux-gnu/libjemalloc.so.2:/opt/libtrace.so") == "/opt/libtrace.so"
    assert worker_preload("libtcmalloc_minimal.so.4 libfoo.so") == "libfoo.so"
    assert worker_preload("/home/me/jemalloc/libbar.so") == "/home/me/jemalloc/libbar.so"


def _report_allocator(conn) -> None:
    enter_child("vigs-test")
    send(conn, (allocator(), os.environ.get("LD_PRELOAD")))


def test_a_worker_child_of_a_process_with_jemalloc_preloaded_uses_glibc(monkeypatch):
    # where jemalloc is not installed the dynamic linker ignores the name (with a warning): the child's own
    # LD_PRELOAD still shows whether it was passed on
    lib = ctypes.util.find_library("jemalloc") or "libjemalloc.so.2"
    monkeypatch.setenv("LD_PRELOAD", lib)
    channel = ChildChannel(_report_allocator, (), "vigs-test")
    try:
        assert os.environ["LD_PRELOAD"] == lib                  # the caller's environment is as it was
        assert channel.receive() == ("libc", "")
    finally:
        channel.close(timeout_s=5)


ARENAS = """
import ctypes, sys, threading
from vigs_core import heap
if sys.argv[1] == "single":
    assert heap.single_arena()
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
together = threading.Barrier(4)
def work():
    together.wait()
    libc.malloc(1 << 16)   # kept: the thread's heap stays in use
    together.wait()
threads = [threading.Thread(target=work) for _ in range(4)]
[t.start() for t in threads]
[t.join() for t in threads]
libc.malloc_stats()   # one "Arena N:" paragraph per heap, on stderr
"""


def _arenas(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", ARENAS, mode], capture_output=True, text=True, check=True,
                         env={**os.environ, "LD_PRELOAD": ""})
    return sum(line.startswith("Arena ") for line in out.stderr.splitlines())


def test_single_arena_serves_every_thread_from_the_main_heap():
    assert _arenas("default") > 1    # glibc's default: a heap for each thread that allocates
    assert _arenas("single") == 1


def test_peak_rss_is_this_process_high_water_mark():
    status = "Name:\tpython\nVmPeak:\t 2000000 kB\nVmHWM:\t  524288 kB\nVmRSS:\t  400000 kB\n"
    assert heap.peak_rss_mb(status) == 512.0
    assert 10 < heap.peak_rss_mb() < 100_000   # this process, read from /proc


PEAK = """
import subprocess, sys
from vigs_core import heap
held = bytearray(300 << 20)   # 300 MB resident in the caller when it starts the child
child = subprocess.run([sys.executable, "-c", "from vigs_core import heap; print(heap.peak_rss_mb())"],
                       capture_output=True, text=True, check=True)
print(heap.peak_rss_mb(), float(child.stdout))
"""


def test_a_started_process_does_not_report_its_callers_memory():
    # Linux carries ru_maxrss across exec: a child forked from a large caller would report the caller's size
    out = subprocess.run([sys.executable, "-c", PEAK], capture_output=True, text=True, check=True)
    caller, child = map(float, out.stdout.split())
    assert caller > 300 and child < caller - 200
