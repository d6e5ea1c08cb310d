"""The Gaussian mapper in a child process: the caller side of :class:`~vigs_core.mapping.mapper.GaussianMapper`
that ``vigs run`` and loop closure use (``add_keyframe``, ``update_keyframe_poses``, ``wait_idle``, ``stop``,
``drain``, ``summary``, ``evaluate``, ``refine``, ``save``, ``snapshot``, ``close``), with the mapper and its
worker thread in a separate Python process.

Why a process: as a thread of the tracking process the mapper's Python work (step scheduling, densification,
the optimiser's bookkeeping) takes the interpreter lock from tracking between its compiled kernels, and its
allocator policy (:func:`vigs_core.heap.retain_freed_heap`, the whole process's heap kept at its peak) applied
to tracking's memory too. A child shares neither; it runs at a lower scheduling priority (``nice``) so that on a
saturated machine tracking keeps its core.

Protocol (one duplex pipe, messages handled in order by the child):

* ``("keyframe", id, T_WC, image, depth, t_ns)`` and ``("poses", {id: T_WC}, {id: scale})``: queued on the
  child's mapper, no answer (an error is kept and raised by the next call);
* ``("call", name, args)``: one of :data:`_CALLS` on the child's mapper, answered ``("return", value)`` or
  ``("error", text)``. ``close`` stops the worker, removes the keyframe store's folder and ends the child.

The parent never blocks on writing: messages are pickled on the caller's thread and written by a sender thread
(as :mod:`vigs_core.loop.process`). Only the caller's thread reads, and only the answer to its own call, so the
child never writes unasked. Tensors travel as NumPy arrays.

Signals: the parent, not a signal, decides when the mapper drains and saves. The child leaves the parent's
process group, so Ctrl-C in a terminal and a SIGTERM to the group (``kill -- -PGID``, ``timeout``) reach only
the parent, which then drains and saves the map through the pipe; it also ignores SIGINT. A SIGTERM sent to the
child itself ends it (multiprocessing terminates its daemon children so at the parent's exit), and so does the
pipe closing (the parent died).
"""
from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import queue
import signal
import threading
import traceback
from pathlib import Path
from typing import Any, Callable, Iterable

import torch

from vigs_core.arrays import host
from vigs_core.mapping.gaussians import GaussianMap
from vigs_core.mapping.mapper import GaussianMapper, MapperConfig, MapperSummary
from vigs_core.process_name import set_process_name


class MappingProcessError(RuntimeError):
    """The mapping process failed (the text of its error) or ended."""


_CALLS: dict[str, Callable[..., Any]] = {
    "wait_idle": GaussianMapper.wait_idle,
    "stop": GaussianMapper.stop,
    "drain": GaussianMapper.drain,
    "summary": GaussianMapper.summary,
    "evaluate": GaussianMapper.evaluate,
    "refine": GaussianMapper.refine,
    "save": GaussianMapper.save,
    "snapshot": GaussianMapper.snapshot,
    "close": GaussianMapper.close,
}


def _child(conn: Any, config: MapperConfig, camera: Any, device: str, nice: int) -> None:
    """The child process: a :class:`GaussianMapper` on its worker thread, driven by the parent's messages."""
    import cv2

    os.setpgid(0, 0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    set_process_name("vigs-mapper")
    if nice:
        os.nice(nice)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    mapper = GaussianMapper(config, camera, device)
    mapper.run_async()
    try:
        _serve(conn, mapper)
    finally:
        mapper.close()   # removes the keyframe store's folder (a child exits without atexit handlers)


def _serve(conn: Any, mapper: GaussianMapper) -> None:
    error: str | None = None   # of a queued message, raised by the next call
    while True:
        try:
            msg = pickle.loads(conn.recv_bytes())
        except EOFError:   # the parent went away
            return
        kind = msg[0]
        try:
            if kind == "keyframe":
                mapper.add_keyframe(*msg[1:])
            elif kind == "poses":
                mapper.update_keyframe_poses(msg[1], msg[2])
        except Exception:   # noqa: BLE001 - handed to the parent with the next call's answer
            error = error or traceback.format_exc()
        if kind != "call":
            continue
        _, name, args = msg
        try:
            if error is not None:
                answer, error = ("error", error), None
            else:
                value = _CALLS[name](mapper, *args)
                answer = ("return", _to_host(value))
        except Exception:   # noqa: BLE001 - raised in the parent by the call
            answer = ("error", traceback.format_exc())
        conn.send_bytes(pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL))
        if name == "close":
            return


def _to_host(value: Any) -> Any:
    """A snapshot's tensors as NumPy arrays (pickled about 20x faster than tensors); other answers as they are."""
    if isinstance(value, GaussianMap):
        return {name: host(getattr(value, name)) for name in value.__dataclass_fields__}
    return value


class MapperProcess:
    """:class:`GaussianMapper`'s caller side with the mapper in a child process (module docstring).

    Args:
        config: the mapper's settings.
        camera: undistorted pinhole camera of the keyframe images (picklable).
        device: torch device of the child's map.
        nice: niceness increment of the child process.
    """

    def __init__(self, config: MapperConfig, camera: Any, device: torch.device | str = "cpu", nice: int = 0) -> None:
        self.config = config
        ctx = mp.get_context("spawn")   # no fork of a process that runs threads
        self._conn, child_conn = ctx.Pipe()
        self._process = ctx.Process(target=_child, args=(child_conn, config, camera, str(device), nice),
                                    name="vigs-mapper", daemon=True)
        self._process.start()
        child_conn.close()
        self._outbox: queue.Queue = queue.Queue()
        self._sender = threading.Thread(target=self._write, name="mapper-sender", daemon=True)
        self._sender.start()
        self._closed = False

    # ------------------------------------------------------------------ feeding (no answer)
    def add_keyframe(self, kf_id: int, T_WC: Any, image: Any, depth: Any, timestamp_ns: int | None = None) -> None:
        """Queue a keyframe on the child's mapper (:meth:`GaussianMapper.add_keyframe`)."""
        self._post(("keyframe", int(kf_id), host(T_WC), host(image), host(depth), timestamp_ns))

    def update_keyframe_poses(self, poses: dict[int, Any], scales: dict[int, float] | None = None) -> None:
        """Queue corrected keyframe poses and depth scales (:meth:`GaussianMapper.update_keyframe_poses`)."""
        self._post(("poses", {int(k): host(T) for k, T in poses.items()},
                    {int(k): float(s) for k, s in (scales or {}).items()}))

    # ------------------------------------------------------------------ calls (answered in order)
    def wait_idle(self) -> None:
        self._call("wait_idle")

    def stop(self) -> None:
        self._call("stop")

    def drain(self, seconds: float) -> int:
        return self._call("drain", float(seconds))

    def summary(self) -> MapperSummary:
        return self._call("summary")

    def evaluate(self, views: Iterable[tuple[Any, Any]]) -> dict:
        return self._call("evaluate", [(host(T), host(image)) for T, image in views])

    def refine(self, iterations: int) -> None:
        self._call("refine", int(iterations))

    def save(self, path: str | Path) -> Path:
        return self._call("save", Path(path))

    def snapshot(self) -> GaussianMap:
        fields = self._call("snapshot")
        return GaussianMap(**{name: torch.from_numpy(a) for name, a in fields.items()})

    def close(self) -> None:
        """Stop the child's mapper, remove its keyframe store and end the child (also when it already ended)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._process.is_alive():
                self._call("close")
        finally:
            self._outbox.put(None)
            self._sender.join()
            self._process.join(timeout=10)
            if self._process.is_alive():
                self._process.terminate()
            self._conn.close()

    # ------------------------------------------------------------------ the pipe
    def _post(self, msg: tuple) -> None:
        if self._closed:
            raise MappingProcessError("the mapping process was closed")
        self._outbox.put(pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL))

    def _write(self) -> None:
        while (data := self._outbox.get()) is not None:
            try:
                self._conn.send_bytes(data)
            except OSError:   # the child is gone; the next call says so
                return

    def _call(self, name: str, *args: Any) -> Any:
        self._outbox.put(pickle.dumps(("call", name, args), protocol=pickle.HIGHEST_PROTOCOL))
        try:
            kind, value = pickle.loads(self._conn.recv_bytes())
        except (EOFError, OSError) as err:
            self._process.join(timeout=1)
            raise MappingProcessError(f"the mapping process ended (exit code {self._process.exitcode})") from err
        if kind == "error":
            raise MappingProcessError(f"mapping failed in its process:\n{value}")
        return value
