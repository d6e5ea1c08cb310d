"""Which malloc a process uses, from its mapped libraries: the report records it, and the glibc policies of
:mod:`vigs_core.heap` do nothing under another one."""
import ctypes.util
import os
import subprocess
import sys

import pytest

from vigs_core.heap import allocator

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


def test_a_process_with_jemalloc_preloaded_says_so_and_sets_no_glibc_policy():
    lib = ctypes.util.find_library("jemalloc")
    if lib is None:
        pytest.skip("libjemalloc is not installed (apt install libjemalloc2)")
    code = "from vigs_core.heap import allocator, map_large_blocks; print(allocator(), map_large_blocks())"
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "LD_PRELOAD": lib}, check=True,
                         capture_output=True, text=True).stdout.split()
    assert out == ["jemalloc", "False"]
