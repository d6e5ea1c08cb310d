"""Loop closure in a child process: the caller-side interface of :class:`~vigs_core.loop.closure.LoopClosure`
(``add_keyframe``, ``pending``, ``start_pgba``, ``poll``, ``record_applied``, ``unit``, ``wait``, ``close``,
``stats``) with detection, verification and PGBA running in a separate Python process.

Why a process: on the 2-core CPU this project targets, the loop-closure worker *thread* shares the interpreter
lock with tracking. Its Python-heavy work (two-view refinement, PGBA's small tensor operations) made tracking
wait for the lock: on hybrid MH_03 (vision only) the main thread took 145 s with the loop thread against 118 s
without loop closure, although the worker needs well under one core. A child process shares no lock with
tracking; it runs at a lower scheduling priority (``LoopConfig.process_nice``) so that on a saturated machine
tracking keeps its core and loop closure uses what is left. The child is started at the ``min_keyframe_gap``-th
keyframe, the first that could have a loop candidate (the messages before wait pickled in the caller, about 10 MB
at 376x240, and are written first): a shorter run, such as the shipped sample, does not pay for a second interpreter
importing torch.

Protocol (one duplex pipe, messages handled in order by the child, an ``inline`` :class:`LoopClosure` there):

* ``("views", [(id, T_WC, disp or None, unit, image or None, revision, depth_scale)])``: keyframe views new or
  changed since last sent, with image and disparities where the view carries them (its first view, and the
  disparities' last revision when the keyframe left the frontend's window: :meth:`LoopClosureDriver.
  _current_views`). The child's detector keeps them on arrival (:meth:`LoopDetector.keep`, spilled to disk when
  old); the uniform depth scalings that follow travel as ``depth_scale``;
* ``("keyframe", id, history_ids, information, metric)``: :meth:`LoopClosure.add_keyframe` on the child's
  views; the information must be picklable (:class:`vigs_core.loop.driver.OdometryEdgeInformation` is);
* ``("pgba", poses)``, ``("applied", scales)``, ``("sync",)``, ``("close",)``.

The pipe, its sender thread (the caller waits only when the child lags far behind, reading the child's answers
meanwhile) and the signal handling are :mod:`vigs_core.child_process`'s. Tensors travel as NumPy arrays
(:func:`vigs_core.arrays.host`): NumPy pickles only the elements of a view of a larger batch (keyframe views, PGBA
corrections), not its whole storage, and about 20 times faster than torch pickles a tensor (8 s of the main
thread on hybrid MH_03 before).

The child answers every message with ``("state", loops_found, loops_covered)`` (``loops_covered``: the loops
in the graph of the last PGBA it started), ``("result", PGBAResult)`` after a PGBA, ``("error", text)`` when a
job raised, and ``("synced", stats)`` / ``("closed", stats)`` (its :class:`LoopStats`, with the child's own peak
memory). Loops are pending while ``loops_found > loops_covered``.
"""
from __future__ import annotations

import traceback
from dataclasses import replace
from typing import Any, Sequence

import torch

from vigs_core.arrays import host
from vigs_core.child_process import ChildChannel, ChildProcessEnded, enter_child, messages, send
from vigs_core.frontend.correspondence import PixelGrid
from vigs_core.frontend.dis_flow import DISFlowConfig, DISFlowEstimator
from vigs_core.gc_freeze import freeze_startup_objects
from vigs_core.heap import map_large_blocks, peak_rss_mb
from vigs_core.loop.closure import InformationSource, LoopClosure, LoopStats
from vigs_core.loop.config import LoopConfig
from vigs_core.loop.detection import KeyframeView
from vigs_core.loop.pgba import PGBAResult
from vigs_core.solver import Intrinsics


def _child(conn: Any, config: LoopConfig, grid: PixelGrid, flow: DISFlowConfig, intr: Intrinsics) -> None:
    """The child process: an inline :class:`LoopClosure` driven by the parent's messages (module docstring)."""
    enter_child("vigs-loop", config.process_nice)
    map_large_blocks()   # image-sized temporaries must not fragment the heap over a long run
    closure = LoopClosure(replace(config, asynchronous=False), DISFlowEstimator(grid, flow), intr)
    freeze_startup_objects()
    try:
        _serve(conn, closure)
    finally:
        closure.close()   # removes the detector's spill folder (a child exits without atexit handlers)


def _serve(conn: Any, closure: LoopClosure) -> None:
    views: dict[int, KeyframeView] = {}   # without image and disparities: the detector keeps those on arrival
    covered = 0
    for msg in messages(conn):
        kind = msg[0]
        try:
            if kind == "views":
                for k, T_WC, disp, unit, image, revision, depth_scale in msg[1]:
                    view = KeyframeView(k, image, torch.from_numpy(T_WC),
                                        None if disp is None else torch.from_numpy(disp), unit, revision, depth_scale)
                    closure.detector.keep(view)
                    views[k] = view.bare()
            elif kind == "keyframe":
                _, k, history, information, metric = msg
                closure.add_keyframe(views[k], [views[i] for i in history], information, metric)
            elif kind == "pgba" and not closure.start_pgba({k: torch.from_numpy(T) for k, T in msg[1].items()}):
                send(conn, ("result", None))
            elif kind == "applied":
                closure.record_applied(msg[1])
            result = closure.poll()   # re-raises a job's error
            if result is not None:
                covered = result.loops
                send(conn, ("result", replace(result, corrections={k: host(C) for k, C in
                                                                    result.corrections.items()})))
        except Exception:   # noqa: BLE001 - handed to the parent, which raises it from poll()
            send(conn, ("error", traceback.format_exc()))
        send(conn, ("state", closure.stats.loops_found, covered))
        if kind in ("sync", "close"):
            closure.stats.process_peak_rss_mb = round(peak_rss_mb(), 1)
            send(conn, ("synced" if kind == "sync" else "closed", closure.stats))
        if kind == "close":
            return


class LoopClosureProcess:
    """:class:`LoopClosure`'s caller side with the work in a child process (module docstring).

    Args:
        config: loop-closure settings (``process_nice``: the child's niceness increment).
        grid: the keyframes' depth grid; flow: DIS settings of the child's correspondence estimator.
        intrinsics: pinhole intrinsics of the keyframe images.
    """

    def __init__(self, config: LoopConfig, grid: PixelGrid, flow: DISFlowConfig, intrinsics: Intrinsics) -> None:
        self.config = config
        self.stats = LoopStats()
        self.units: dict[int, float] = {}
        # started once loops become possible (min_keyframe_gap keyframes): a shorter run never pays for the child
        self._channel = ChildChannel(_child, (config, grid, flow, intrinsics), "vigs-loop-closure",
                                     while_waiting=self._drain, start=config.detection.min_keyframe_gap == 0)
        self._sent: dict[int, torch.Tensor] = {}   # id -> the pose tensor of the view last sent
        self._found = 0
        self._covered = 0
        self._in_flight = False
        self._result: PGBAResult | None = None
        self._error: str | None = None

    # ------------------------------------------------------------------ messages to and from the child
    def _post(self, msg: tuple) -> None:
        self._channel.post(msg)

    def _handle(self, msg: tuple) -> None:
        kind = msg[0]
        if kind == "state":   # an answer sent before the child started the PGBA posted last covers fewer loops
            self._found, self._covered = msg[1], max(self._covered, msg[2])
        elif kind in ("synced", "closed"):
            self.stats = replace(msg[1], queue_wait_seconds=self._channel.waited_s)
        elif kind == "result":
            result = msg[1]
            if result is not None:
                result = replace(result, corrections={k: torch.from_numpy(C) for k, C in result.corrections.items()})
            self._result, self._in_flight = result, False
        elif kind == "error":
            self._error, self._in_flight = msg[1], False

    def _receive(self) -> tuple:
        try:
            return self._channel.receive()
        except ChildProcessEnded as err:
            raise RuntimeError(f"the loop-closure {err}") from err

    def _drain(self) -> None:
        while self._channel.conn.poll(0):
            self._handle(self._receive())

    def _await(self, kind: str) -> None:
        while (msg := self._receive())[0] != kind:
            self._handle(msg)
        self._handle(msg)

    # ------------------------------------------------------------------ LoopClosure's caller side
    def add_keyframe(self, new: KeyframeView, history: Sequence[KeyframeView],
                     odometry_information: InformationSource = None, metric: bool = False) -> None:
        """Send the views not yet in the child or changed since (with what they carry, see the module docstring)
        and queue ``new`` for detection there (the child is started at the ``min_keyframe_gap``-th keyframe, the
        first that could have a loop candidate; the earlier ones wait here, pickled)."""
        changed = []   # (id, T_WC, disp or None, unit, image or None, revision, depth_scale)
        for v in (*history, new):
            if self._sent.get(v.id) is not v.T_WC or v.disp is not None or v.image is not None:
                changed.append((v.id, host(v.T_WC), None if v.disp is None else host(v.disp), v.unit, v.image,
                                v.revision, v.depth_scale))
                self._sent[v.id] = v.T_WC
        if changed:
            self._post(("views", changed))
        self._post(("keyframe", new.id, [v.id for v in history], odometry_information, metric))
        if len(self._sent) >= self.config.detection.min_keyframe_gap:   # every keyframe so far has been sent
            self._channel.start()

    @property
    def pending(self) -> bool:
        """Loops accepted by the child that no started PGBA covers yet, and none in flight or waiting to be
        polled (so the caller builds PGBA's pose snapshot only when :meth:`start_pgba` will take it)."""
        self._drain()
        return self._found > self._covered and not self._in_flight and self._result is None

    def start_pgba(self, poses: dict[int, torch.Tensor]) -> bool:
        """Queue PGBA in the child when :attr:`pending`; True when queued."""
        if not self.pending:
            return False
        self._post(("pgba", {k: host(T) for k, T in poses.items()}))
        self._covered = self._found   # until the child says which loops its graph held
        self._in_flight = True
        return True

    def record_applied(self, scales: dict[int, float]) -> None:
        """Corrections with depth scales ``{id: c}`` were applied (see :meth:`LoopClosure.record_applied`)."""
        for k, c in scales.items():
            self.units[k] = self.units.get(k, 1.0) * float(c)
        self._post(("applied", {k: float(c) for k, c in scales.items()}))

    def unit(self, kf_id: int) -> float:
        """Current depth units of a keyframe (product of the applied correction scales)."""
        return self.units.get(kf_id, 1.0)

    def poll(self) -> PGBAResult | None:
        """A finished PGBA's corrections (once), else None; raises an error of the child."""
        self._drain()
        if self._error is not None:
            err, self._error = self._error, None
            raise RuntimeError(f"loop closure failed in its worker process:\n{err}")
        out, self._result = self._result, None
        return out

    def wait(self) -> PGBAResult | None:
        """Block until the child has handled every message sent so far, then :meth:`poll`."""
        if not self._channel.started:   # nothing can have been found yet
            return self.poll()
        self._post(("sync",))
        self._await("synced")
        return self.poll()

    def close(self) -> None:
        """Let the child finish its queue and exit."""
        try:
            if self._channel.started and self._channel.process.is_alive():
                self._post(("close",))
                self._await("closed")
        finally:
            self._channel.close()
