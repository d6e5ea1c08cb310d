"""Reading and preparing input frames on a thread ahead of tracking (the role a camera driver plays live).

:class:`FramePrefetcher` iterates a frame source (``(t_ns, raw image)`` in time order) on a reader thread, applies
``prepare(k, raw)`` (decode, undistort, resize; ``None`` for frames to skip) and hands ``(t_ns, prepared)`` over a
bounded queue, so reading images from disk or a bag overlaps with tracking on the other core instead of adding to
its time per frame (OpenCV's decoding and remapping release the interpreter lock). Order is kept; an exception
of the source or of ``prepare`` is raised to the consumer at the frame where it happened.
"""
from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator
from typing import Any, Callable

_END = object()


class FramePrefetcher:
    """Iterator of ``(t_ns, prepare(k, raw))`` over at most ``count`` frames of ``frames`` (module docstring).

    Args:
        frames: the source iterator of ``(t_ns, raw image)``.
        prepare: ``(frame index, raw image) -> prepared frame`` or None for a skipped frame; runs on the reader.
        count: read at most this many frames (None: all).
        depth: frames read ahead at most (bounds the memory held).

    Attributes:
        reader_seconds: time the reader thread spent reading and preparing (off the consumer's thread).
    """

    def __init__(self, frames: Iterator[tuple[int, Any]], prepare: Callable[[int, Any], Any],
                 count: int | None = None, depth: int = 8) -> None:
        self.reader_seconds = 0.0
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(frames, prepare, count), name="frame-reader",
                                        daemon=True)
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _read(self, frames: Iterator, prepare: Callable, count: int | None) -> None:
        try:
            k = 0
            while count is None or k < count:
                t0 = time.perf_counter()
                try:
                    t_ns, raw = next(frames)
                except StopIteration:
                    break
                item = (t_ns, prepare(k, raw))
                self.reader_seconds += time.perf_counter() - t0
                if not self._put(item):
                    return
                k += 1
            self._put(_END)
        except BaseException as err:   # handed to the consumer
            self._put(err)

    def __iter__(self) -> "FramePrefetcher":
        return self

    def __next__(self) -> tuple[int, Any]:
        item = self._queue.get()
        if item is _END:
            self._queue.put(_END)   # stays exhausted
            raise StopIteration
        if isinstance(item, BaseException):
            self._queue.put(item)   # raised again on a further call
            raise item
        return item

    def close(self) -> None:
        """Stop the reader (frames not consumed are dropped)."""
        self._stop.set()
        self._thread.join()
