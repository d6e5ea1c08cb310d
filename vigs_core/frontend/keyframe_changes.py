"""What a consumer of the frontend's keyframes (the mapping feed, the ROS frontend's keyframe updates) last sent of
each keyframe, and how much the keyframe has changed since: the pose, and the factor ``c`` by which its depths grew.

The frontend replaces a keyframe's pose tensor when it changes it (never edits it), re-estimates its disparities
only while it is in the window (a new :attr:`~vigs_core.frontend.odometry.Keyframe.revision`) and afterwards
only scales its depths uniformly (:attr:`~vigs_core.frontend.odometry.Keyframe.depth_scale`). So a keyframe is
unchanged while its pose tensor, revision and depth scale are; within one revision ``c`` is the ratio of depth
scales; across revisions it is the median per-cell ratio of the disparities (:func:`depth_scale_change`). The
disparities of the reference are kept only until the keyframe settles (its disparities dropped by the
frontend), so a long run keeps no per-keyframe arrays here.

A long run keeps thousands of keyframes of which a frame changes a few (BA's window, a keyframe settling), so
consumers do not compare every keyframe every frame: the odometry's keyframes live in a :class:`KeyframeTable`,
which notes in a :class:`KeyframeChanges` log every keyframe put into it and every later assignment to one of
its :data:`WATCHED` attributes (:meth:`~vigs_core.frontend.odometry.Keyframe.__setattr__`); the odometry also
notes a keyframe leaving its window (the loop driver's views depend on it). Each consumer takes the ids noted
since it last looked from its own :class:`ChangeCursor`; since every replacement of a keyframe's tensors is an
assignment, no change escapes the log, whichever code made it.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any, Iterable

import torch

WATCHED = frozenset(("pose", "disp", "revision", "depth_scale", "image"))
"""Keyframe attributes whose assignment is a change for the consumers (what :meth:`SentKeyframes.change`
compares, and the pixels dropped when a keyframe settles)."""


def depth_scale_change(d_old: torch.Tensor, d_new: torch.Tensor) -> float:
    """The scale ``c = median(d_old / d_new)`` by which a keyframe's depths grew between two versions of its
    disparities (cells positive in both; 1 without any): ``c = s`` for a world rescaled by ``s``."""
    ok = (d_old > 0) & (d_new > 0)
    return float(torch.median(d_old[ok] / d_new[ok])) if bool(ok.any()) else 1.0


@dataclass
class _Reference:
    """``T_WC``: the pose last sent (as the consumer gave it); ``disp`` (revision ``revision``, at the keyframe's depth scale
    ``depth_scale`` then; None once settled) with ``ratio`` = its depths / the depths last sent; ``seen_pose``,
    ``seen_revision``, ``seen_scale``: the keyframe's pose tensor, revision and depth scale last compared."""

    T_WC: Any
    disp: torch.Tensor | None
    revision: int
    depth_scale: float
    ratio: float
    seen_pose: torch.Tensor
    seen_revision: int
    seen_scale: float


class SentKeyframes:
    """Keyframe id -> what was last sent of it (module docstring). Keyframes are the frontend's
    :class:`~vigs_core.frontend.odometry.Keyframe` objects (``id``, ``pose``, ``disp``, ``revision``,
    ``depth_scale``)."""

    def __init__(self) -> None:
        self._refs: dict[int, _Reference] = {}

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._refs

    def record(self, kf: Any, T_WC: Any) -> None:
        """``kf`` was sent now, at pose ``T_WC`` (4, 4; a tensor or an array) and its current depths."""
        self._refs[kf.id] = _Reference(T_WC, kf.disp, kf.revision, kf.depth_scale, 1.0, kf.pose, kf.revision,
                                       kf.depth_scale)

    def change(self, kf: Any) -> tuple[Any, float] | None:
        """None when ``kf`` is unchanged since the last call (or :meth:`record`); else the pose last sent and
        ``c`` = current depths / depths last sent."""
        ref = self._refs[kf.id]
        if kf.disp is None:
            ref.disp = None   # settled: no revision follows
        if kf.pose is ref.seen_pose and kf.revision == ref.seen_revision and kf.depth_scale == ref.seen_scale:
            return None   # called for every keyframe at every frame: no allocation on this path
        ref.seen_pose, ref.seen_revision, ref.seen_scale = kf.pose, kf.revision, kf.depth_scale
        if kf.revision != ref.revision:
            if ref.disp is None or kf.disp is None:
                raise RuntimeError(f"keyframe {kf.id}: disparities re-estimated after it left the window")
            ref.ratio *= depth_scale_change(ref.disp, kf.disp)
            ref.disp, ref.revision, ref.depth_scale = kf.disp, kf.revision, kf.depth_scale
        return ref.T_WC, ref.ratio * kf.depth_scale / ref.depth_scale


class ChangeCursor:
    """One consumer's view of a :class:`KeyframeChanges` log: the keyframe ids noted since its last :meth:`take`."""

    def __init__(self, ids: Iterable[int]) -> None:
        self._ids: set[int] = set(ids)

    def take(self) -> list[int]:
        """The ids noted since the last call (ascending), forgotten here."""
        ids, self._ids = sorted(self._ids), set()
        return ids


class KeyframeChanges:
    """The log of keyframe changes, fanned out to every subscribed :class:`ChangeCursor` that is still in use (held
    weakly: a consumer dropped before the odometry does not keep collecting ids)."""

    def __init__(self) -> None:
        self._cursors: weakref.WeakSet[ChangeCursor] = weakref.WeakSet()

    def note(self, kf_id: int) -> None:
        for cursor in self._cursors:
            cursor._ids.add(kf_id)

    def subscribe(self, existing: Iterable[int]) -> ChangeCursor:
        """A cursor whose first :meth:`ChangeCursor.take` lists the ``existing`` keyframes too, so a consumer
        that subscribes late sees every keyframe once."""
        cursor = ChangeCursor(existing)
        self._cursors.add(cursor)
        return cursor


class KeyframeTable(dict):
    """Keyframe id -> keyframe, noting in :attr:`changes` every keyframe put in and binding it to the log, so
    that assignments to its :data:`WATCHED` attributes are noted too (module docstring)."""

    def __init__(self) -> None:
        super().__init__()
        self.changes = KeyframeChanges()

    def __setitem__(self, kf_id: int, kf: Any) -> None:
        object.__setattr__(kf, "changes", self.changes)
        super().__setitem__(kf_id, kf)
        self.changes.note(kf_id)

    def subscribe(self) -> ChangeCursor:
        """A consumer's cursor (:meth:`KeyframeChanges.subscribe`), starting with every keyframe held now."""
        return self.changes.subscribe(iter(self))
