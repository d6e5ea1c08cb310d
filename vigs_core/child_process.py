"""A worker in a spawned child process, as ``vigs run`` runs loop closure and mapping: the caller's side
(:class:`ChildChannel`: the process, a duplex pipe to it and a sender thread) and the child's first step
(:func:`enter_child`).

The caller does not write to the pipe itself: messages are pickled on the caller's thread (the standard pickler,
``send_bytes``: multiprocessing's own would hand every torch tensor over in shared memory, one segment per
tensor) and written by the sender thread, so the child can always answer; a 7 MB batch of keyframe views and the
child's answers once filled both pipe buffers and deadlocked both sides when the caller wrote them itself. The
sender's queue is bounded: a child that lags behind (a niced worker on a saturated machine) made it grow without
end (tens of MB of keyframe images in the caller). Past ``max_queued_bytes`` :meth:`ChildChannel.post` waits for
the sender, and reads the child's answers meanwhile through the caller's ``while_waiting``, so neither side
waits on a full pipe.

The child leaves the parent's process group and ignores SIGINT: Ctrl-C in a terminal and a SIGTERM to the group
(``kill -- -PGID``, ``timeout``) reach only the parent, which finishes the run with its workers still there (a group
SIGTERM had ended the loop-closure child and then the run, its outputs unwritten). Both signals are blocked from
the child's start until it has left the group, and a group SIGTERM that arrived meanwhile (the child spends about
a second importing its modules) is discarded there. A SIGTERM to the child itself ends it (multiprocessing
terminates its daemon children so at the parent's exit), and so does the pipe closing (the parent died). Its
process name (``/proc/PID/comm``) tells ``ps`` and ``vigs bench soak`` which worker it is: spawned children all
run the same command line. A malloc preloaded for the caller (jemalloc) is not preloaded for the child
(:func:`vigs_core.heap.worker_preload`); glibc's serves all of the child's threads from one heap
(:func:`vigs_core.heap.single_arena`).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing as mp
import os
import pickle
import queue
import signal
import threading
import time
from multiprocessing import resource_tracker
from typing import Any, Callable, Iterator

from vigs_core.heap import single_arena, worker_preload

_PR_SET_NAME = 15   # prctl(2)
MAX_QUEUED_BYTES = 8 << 20
"""Default bound of a :class:`ChildChannel`'s queue: about 90 keyframe images at 376x240, far above what a child
that keeps up leaves queued (about 1.5 MB for loop closure on the procedural soak)."""


class ChildProcessEnded(RuntimeError):
    """The child ended while the caller waited for its answer (the message says ``process ended (exit code N)``)."""


def enter_child(name: str, nice: int = 0) -> None:
    """First step of a worker child: its own process group, SIGINT ignored, SIGTERM unblocked (a SIGTERM sent to the
    parent's group before this point is discarded: setting a pending signal to ignored drops it), the process name
    ``name``, the niceness increment ``nice``, one thread each for torch and OpenCV (the workers share 2 cores
    with tracking), and one malloc heap for its threads (:func:`vigs_core.heap.single_arena`)."""
    import cv2
    import torch

    single_arena()
    os.setpgid(0, 0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    set_process_name(name)
    if nice:
        os.nice(nice)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)


def set_process_name(name: str) -> bool:
    """Set this process's name (Linux: at most 15 bytes are kept); False where prctl is not available."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        return libc.prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def send(conn: Any, msg: tuple) -> None:
    """Write one message (the child's side; the caller posts through :meth:`ChildChannel.post`)."""
    conn.send_bytes(pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL))


def receive(conn: Any) -> tuple:
    """Read one message (EOFError when the other side closed the pipe)."""
    return pickle.loads(conn.recv_bytes())


def messages(conn: Any) -> Iterator[tuple]:
    """The child's loop over the parent's messages, until the pipe closes (the parent went away)."""
    while True:
        try:
            yield receive(conn)
        except EOFError:
            return


class ChildChannel:
    """A daemon child ``target(conn, *args)`` started with the spawn method (no fork of a process that runs
    threads), named ``name``, and the caller's end of its pipe.

    Args:
        target, args, name: the child's function, its arguments after the pipe, and the process name.
        max_queued_bytes: what the sender's queue may hold before :meth:`post` waits (module docstring).
        while_waiting: called repeatedly while :meth:`post` waits, to read what the child sends unasked (None:
            the child only answers calls, which the caller reads after posting them).
        start: start the child now; False defers it to :meth:`start` (a worker that cannot be useful yet): the
            messages posted meanwhile are kept, pickled, and written first, in order. That backlog is the caller's
            to bound (the loop-closure caller's is its first keyframes' messages); :meth:`post` waits only for
            what is queued beyond the part of it not yet written.

    Attributes:
        process: the child (``multiprocessing.Process``).
        conn: the caller's end of the pipe (``poll``); reading goes through :meth:`receive`, writing through
            :meth:`post`.
        waited_s: seconds :meth:`post` waited for room in the queue.
        started: whether the child was started.
    """

    def __init__(self, target: Callable[..., None], args: tuple, name: str, max_queued_bytes: int = MAX_QUEUED_BYTES,
                 while_waiting: Callable[[], None] | None = None, start: bool = True) -> None:
        ctx = mp.get_context("spawn")
        self.conn, self._child_conn = ctx.Pipe()
        self.process = ctx.Process(target=target, args=(self._child_conn, *args), name=name, daemon=True)
        self.max_queued_bytes = max_queued_bytes
        self.waited_s = 0.0
        self._while_waiting = while_waiting
        self._outbox: queue.Queue = queue.Queue()
        self._queued_bytes = 0
        self._backlog = 0   # bytes of a deferred start's backlog not written yet (not waited for)
        self._count_lock = threading.Lock()
        self._written = threading.Event()
        self._sender = threading.Thread(target=self._write, name=f"{name}-sender", daemon=True)
        self.started = False
        if start:
            self.start()

    def start(self) -> None:
        """Start the child and the sender thread (once; the messages posted before go first)."""
        if self.started:
            return
        self.started = True
        with self._count_lock:
            self._backlog = self._queued_bytes
        # blocked across the start (a blocked signal stays blocked in the new program): a Ctrl-C or a SIGTERM to the
        # group while the child still imports its modules, before enter_child, would otherwise end it. The start
        # launches multiprocessing's resource tracker the first time, which unblocks both after launching it: so
        # launch it before blocking them
        resource_tracker.ensure_running()
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        preload = os.environ.get("LD_PRELOAD")   # the child inherits the environment at its start
        if preload is not None:
            os.environ["LD_PRELOAD"] = worker_preload(preload)
        try:
            self.process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
            if preload is not None:
                os.environ["LD_PRELOAD"] = preload
        self._child_conn.close()
        self._sender.start()

    @property
    def queued_bytes(self) -> int:
        """Bytes of the messages posted and not yet written to the pipe."""
        return self._queued_bytes

    def post(self, msg: tuple) -> None:
        """Queue ``msg`` for the child (pickled now, on the caller's thread); then, while the queue holds more than
        ``max_queued_bytes`` beyond a deferred start's backlog not yet written (see the class) and the child reads,
        wait (calling ``while_waiting``); a child not started yet is not waited for."""
        data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
        with self._count_lock:
            self._queued_bytes += len(data)
        self._outbox.put(data)
        if not self.started or self._queued_bytes <= self.max_queued_bytes + self._backlog:
            return
        t0 = time.perf_counter()
        while self._queued_bytes > self.max_queued_bytes + self._backlog and self._sender.is_alive():
            if self._while_waiting is not None:
                self._while_waiting()
            self._written.wait(0.05)
            self._written.clear()   # the condition is tested after: a write between wait and clear is not missed
        self.waited_s += time.perf_counter() - t0

    def receive(self) -> tuple:
        """The child's next message; :class:`ChildProcessEnded` when the child is gone."""
        if not self.started:
            raise RuntimeError("ChildChannel.receive: the child was not started")
        try:
            return receive(self.conn)
        except (EOFError, OSError) as err:
            self.process.join(timeout=1)
            raise ChildProcessEnded(f"process ended (exit code {self.process.exitcode})") from err

    def close(self, timeout_s: float = 10.0) -> None:
        """After the child was told to end (or ended): stop the sender, wait for the child (terminated after
        ``timeout_s``) and close the pipe. A child never started is not started; its messages are dropped."""
        if not self.started:
            self._child_conn.close()
            self.conn.close()
            return
        self._outbox.put(None)
        self._sender.join()
        self.process.join(timeout=timeout_s)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout=timeout_s)
        self.conn.close()

    def _write(self) -> None:
        while (data := self._outbox.get()) is not None:
            try:
                self.conn.send_bytes(data)
            except OSError:   # the child is gone; the caller's next read says so
                return
            with self._count_lock:
                self._queued_bytes -= len(data)
                self._backlog = max(0, self._backlog - len(data))
            self._written.set()
