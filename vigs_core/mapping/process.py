"""The Gaussian mapper in a child process: the caller side of :class:`~vigs_core.mapping.mapper.GaussianMapper`
that ``vigs run`` and loop closure use (``add_keyframe``, ``update_keyframe_poses``, ``wait_idle``, ``stop``,
``drain``, ``summary``, ``evaluate``, ``refine``, ``save``, ``snapshot``, ``close``, and the child's
``peak_rss_mb``), with the mapper and its worker thread in a separate Python process.

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

The pipe, its sender thread and the signal handling are :mod:`vigs_core.child_process`'s. Only the caller's
thread reads, and only the answer to its own call, so the child never writes unasked (and the caller may wait for
room in the sender's queue without reading). Tensors travel as NumPy arrays.
"""
from __future__ import annotations

import traceback
from pathlib import Path
from typing import Any, Callable, Iterable

import torch

from vigs_core.arrays import host
from vigs_core.child_process import ChildChannel, ChildProcessEnded, enter_child, messages, send
from vigs_core.gc_freeze import freeze_startup_objects
from vigs_core.heap import peak_rss_mb
from vigs_core.mapping.gaussians import GaussianMap
from vigs_core.mapping.mapper import GaussianMapper, MapperConfig, MapperSummary


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
    "peak_rss_mb": lambda mapper: peak_rss_mb(),
}


def _child(conn: Any, config: MapperConfig, camera: Any, device: str, nice: int) -> None:
    """The child process: a :class:`GaussianMapper` on its worker thread, driven by the parent's messages."""
    enter_child("vigs-mapper", nice)
    mapper = GaussianMapper(config, camera, device)
    freeze_startup_objects()
    mapper.run_async()
    try:
        _serve(conn, mapper)
    finally:
        mapper.close()   # removes the keyframe store's folder (a child exits without atexit handlers)


def _serve(conn: Any, mapper: GaussianMapper) -> None:
    error: str | None = None   # of a queued message, raised by the next call
    for msg in messages(conn):
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
        send(conn, answer)
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

    Attributes:
        channel: the child process and its pipe (:class:`~vigs_core.child_process.ChildChannel`).
    """

    def __init__(self, config: MapperConfig, camera: Any, device: torch.device | str = "cpu", nice: int = 0) -> None:
        self.config = config
        self.channel = ChildChannel(_child, (config, camera, str(device), nice), "vigs-mapper")
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
    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until the child's mapper has applied everything queued, or ``timeout`` seconds passed; whether it
        has."""
        return self._call("wait_idle", timeout)

    def stop(self) -> None:
        """Stop the child's worker after the step in hand (queued events stay queued)."""
        self._call("stop")

    def drain(self, seconds: float) -> int:
        """After :meth:`stop`: insert what is queued without refinement for at most ``seconds``; events left."""
        return self._call("drain", float(seconds))

    def peak_rss_mb(self) -> float:
        """The child process's peak resident memory so far, MiB (:func:`vigs_core.heap.peak_rss_mb`)."""
        return self._call("peak_rss_mb")

    def summary(self) -> MapperSummary:
        """Counters and sizes of the child's mapper."""
        return self._call("summary")

    def evaluate(self, views: Iterable[tuple[Any, Any]]) -> dict:
        """Render quality on ``(T_WC, image)`` views (:meth:`GaussianMapper.evaluate`)."""
        return self._call("evaluate", [(host(T), host(image)) for T, image in views])

    def refine(self, iterations: int) -> None:
        """Final colour refinement (:meth:`GaussianMapper.refine`)."""
        self._call("refine", int(iterations))

    def save(self, path: str | Path) -> Path:
        """The child writes the map and its sidecar at ``path``; returns the sidecar path."""
        return self._call("save", Path(path))

    def snapshot(self) -> GaussianMap:
        """A copy of the child's current map."""
        fields = self._call("snapshot")
        return GaussianMap(**{name: torch.from_numpy(a) for name, a in fields.items()})

    def close(self) -> None:
        """Stop the child's mapper, remove its keyframe store and end the child (also when it already ended)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.channel.process.is_alive():
                self._call("close")
        finally:
            self.channel.close()

    # ------------------------------------------------------------------ the pipe
    def _post(self, msg: tuple) -> None:
        if self._closed:
            raise MappingProcessError("the mapping process was closed")
        self.channel.post(msg)

    def _call(self, name: str, *args: Any) -> Any:
        self.channel.post(("call", name, args))
        try:
            kind, value = self.channel.receive()
        except ChildProcessEnded as err:
            raise MappingProcessError(f"the mapping {err}") from err
        if kind == "error":
            raise MappingProcessError(f"mapping failed in its process:\n{value}")
        return value
