"""What waits for the mapper: keyframes in order and keyframe pose corrections folded into one batch.

Tracking sends a keyframe pose update after most bundle adjustments, so a FIFO of events grows with every update
while the mapper is busy, and applying them one by one moves the same Gaussians again and again. The inbox keeps
at most one pending correction per keyframe: anchored moves compose (Eq. 6-7 of VIGS-SLAM: moving a keyframe
T0 -> T1 with scale s1 and then T1 -> T2 with s2 is the move T0 -> T2 with scale s1 s2), so the newest pose and
the product of the scale corrections stand for all of them. A correction of a keyframe still queued is applied to
it in place (it is inserted at its newest pose, its depth rescaled), so what is pending is bounded by the
keyframes queued plus one correction batch.

A live mapper that cannot keep up must not fall further and further behind the robot: with a ``capacity``, the
queue keeps the newest keyframes and moves the oldest aside ("deferred"); they are handed out only when nothing
else waits (the robot idle, or the shutdown drain), newest first. Deferred keyframes cost the memory a mapped
keyframe costs (the mapper's keyframe store), and are counted.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Any

import torch


class MapperInbox:
    """Thread-safe inbox of a :class:`vigs_core.mapping.GaussianMapper` (module docstring).

    :meth:`take` hands out the pending pose corrections first (one ``("poses", poses, scales)`` batch), then the
    oldest queued keyframe, then the newest deferred one (``("keyframe", kf)``); :meth:`done` marks the taken
    event applied.

    Args:
        capacity: keyframes queued at most (older ones are deferred); 0: no limit, nothing is deferred.
    """

    def __init__(self, capacity: int = 0) -> None:
        if capacity < 0:
            raise ValueError(f"capacity must be >= 0, got {capacity}")
        self.capacity = capacity
        self._cond = threading.Condition()
        self._keyframes: deque[Any] = deque()
        self._deferred: list[Any] = []
        self._poses: dict[int, torch.Tensor] = {}
        self._scales: dict[int, float] = {}
        self._busy = 0

    def put_keyframe(self, kf: Any) -> None:
        """Queue a keyframe (an object with ``id``, ``T_WC`` (4, 4) and ``depth_scale``)."""
        with self._cond:
            self._keyframes.append(kf)
            while self.capacity and len(self._keyframes) > self.capacity:
                self._deferred.append(self._keyframes.popleft())
            self._cond.notify_all()

    def put_poses(self, poses: dict[int, torch.Tensor], scales: dict[int, float]) -> None:
        """Fold corrected poses ``{kf_id: T_WC}`` and scale corrections ``{kf_id: s}`` into what is pending."""
        with self._cond:
            waiting = {kf.id: kf for kf in (*self._keyframes, *self._deferred)}
            for k, T in poses.items():
                s = float(scales.get(k, 1.0))
                kf = waiting.get(k)
                if kf is not None:           # not inserted yet: insert it where it is now
                    kf.T_WC = T
                    kf.depth_scale *= s
                    continue
                self._poses[k] = T
                if s != 1.0:
                    self._scales[k] = self._scales.get(k, 1.0) * s
            self._cond.notify_all()

    def take(self, timeout: float | None = 0.0) -> tuple | None:
        """The next event, waiting up to ``timeout`` seconds (None: no limit) for one; None when there is none."""
        with self._cond:
            if not self._cond.wait_for(self._ready, timeout):
                return None
            self._busy += 1
            if self._poses:
                event = ("poses", self._poses, self._scales)
                self._poses, self._scales = {}, {}
                return event
            if self._keyframes:
                return ("keyframe", self._keyframes.popleft())
            return ("keyframe", self._deferred.pop())

    def done(self) -> None:
        """The event from :meth:`take` is applied."""
        with self._cond:
            self._busy -= 1
            self._cond.notify_all()

    def wait_empty(self, timeout: float | None = None) -> bool:
        """Block until nothing is pending or deferred and no taken event is being applied, or ``timeout`` seconds
        passed; whether it is empty."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._ready() and self._busy == 0, timeout)

    def full(self) -> bool:
        """The queue is at its capacity: the next keyframe will defer one (never with no capacity)."""
        with self._cond:
            return bool(self.capacity) and len(self._keyframes) >= self.capacity

    def deferred(self) -> int:
        """Keyframes moved aside, not yet handed out."""
        with self._cond:
            return len(self._deferred)

    def __len__(self) -> int:
        """Events pending, deferred keyframes aside: the queued keyframes plus one for a correction batch."""
        with self._cond:
            return len(self._keyframes) + (1 if self._poses else 0)

    def _ready(self) -> bool:
        return bool(self._poses) or bool(self._keyframes) or bool(self._deferred)
