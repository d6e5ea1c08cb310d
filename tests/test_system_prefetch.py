"""The frame prefetcher: order, skipped frames, the frame limit, errors raised at the frame where they happened,
early close."""
import time

import pytest

from vigs_core.system.prefetch import FramePrefetcher


def source(n, fail_at=None):
    for k in range(n):
        if k == fail_at:
            raise OSError(f"cannot read frame {k}")
        yield 1000 * k, k


def test_frames_arrive_in_order_prepared_and_limited():
    reader = FramePrefetcher(source(50), lambda k, raw: None if k % 3 else raw * 10, count=20, depth=4)
    got = list(reader)
    assert [t for t, _ in got] == [1000 * k for k in range(20)]
    assert [x for _, x in got] == [10 * k if k % 3 == 0 else None for k in range(20)]
    with pytest.raises(StopIteration):
        next(reader)
    reader.close()
    assert reader.reader_seconds >= 0.0


def test_a_source_error_reaches_the_consumer_at_its_frame():
    reader = FramePrefetcher(source(10, fail_at=4), lambda k, raw: raw)
    assert [t for t, _ in (next(reader) for _ in range(4))] == [0, 1000, 2000, 3000]
    with pytest.raises(OSError, match="frame 4"):
        next(reader)
    with pytest.raises(OSError):   # and stays raised
        next(reader)
    reader.close()


def test_close_stops_a_reader_blocked_on_a_full_queue():
    reader = FramePrefetcher(source(10_000), lambda k, raw: raw, depth=2)
    next(reader)
    time.sleep(0.05)   # the reader fills the queue and waits
    t0 = time.perf_counter()
    reader.close()
    assert time.perf_counter() - t0 < 2.0 and not reader._thread.is_alive()
