"""Keyframe arrays kept on disk beyond a bounded resident set, so memory stays bounded over long missions.

Loop closure and the Gaussian mapper read a keyframe's pixels long after it was made (loop verification, the
mapper's random global keyframes), but rarely: a few keyframes per new one. :class:`SpillStore` keeps the
``resident`` most recently used entries in memory and the rest as ``.npy`` files in a private folder (removed
when the store is closed or collected), read back on demand. Per keyframe the process then holds only what
lives outside the store (poses, thumbnails, ids), so resident memory stops growing with the number of keyframes.
Where the folder is on a memory-backed file system (a tmpfs /tmp, the default on Debian 13 and Fedora), the
files still take RAM: the store warns once, naming the folder and the ``directory`` setting.
"""
from __future__ import annotations

import shutil
import tempfile
import threading
import warnings
import weakref
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Hashable

import numpy as np
import psutil

from vigs_core.ranges import bounded


@dataclass
class SpillConfig:
    """Where keyframe arrays live (:class:`SpillStore`).

    Args:
        resident: entries kept in memory at most (the most recently used); older ones are written to disk and
            read back when used. 0: everything stays in memory (no files).
        directory: folder in which the store makes its private spill folder; "" = the system's temporary folder
            (``TMPDIR`` or /tmp). Give a folder on disk where that is a tmpfs.
    """

    resident: int = bounded(64, 0)
    directory: str = ""


class SpillStore:
    """``key -> tuple of arrays`` with at most ``config.resident`` entries in memory (least recently used spill
    first). Thread-safe. Arrays read back are fresh copies; callers must not modify the arrays they put."""

    def __init__(self, config: SpillConfig | None = None, name: str = "spill") -> None:
        self.config = config or SpillConfig()
        self.name = name
        self._resident: OrderedDict[Hashable, tuple[np.ndarray, ...]] = OrderedDict()
        self._spilled: dict[Hashable, int] = {}   # key -> number of arrays in its files
        self._folder: Path | None = None
        self._finalizer: weakref.finalize | None = None
        self._lock = threading.Lock()
        self.reads = 0    # entries read back from disk
        self.writes = 0   # entries written to disk

    def __len__(self) -> int:
        return len(self._resident) + len(self._spilled)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._resident or key in self._spilled

    @property
    def resident_count(self) -> int:
        return len(self._resident)

    def put(self, key: Hashable, *arrays: np.ndarray) -> None:
        """Store ``arrays`` under ``key`` (replacing what was there), as the most recently used entry."""
        with self._lock:
            self._drop(key)
            self._resident[key] = tuple(np.asarray(a) for a in arrays)
            self._evict()

    def get(self, key: Hashable) -> tuple[np.ndarray, ...]:
        """The arrays stored under ``key`` (KeyError if none), read back from disk when spilled."""
        with self._lock:
            if key in self._resident:
                self._resident.move_to_end(key)
                return self._resident[key]
            count = self._spilled.pop(key)
            arrays = tuple(np.load(self._path(key, i)) for i in range(count))
            for i in range(count):
                self._path(key, i).unlink()
            self.reads += 1
            self._resident[key] = arrays
            self._evict()
            return arrays

    def discard(self, key: Hashable) -> None:
        with self._lock:
            self._drop(key)

    def close(self) -> None:
        """Forget everything and remove the spill folder."""
        with self._lock:
            self._resident.clear()
            self._spilled.clear()
            if self._finalizer is not None:
                self._finalizer()
            self._folder = self._finalizer = None

    def _evict(self) -> None:
        if self.config.resident == 0:
            return
        while len(self._resident) > self.config.resident:
            key, arrays = self._resident.popitem(last=False)
            for i, a in enumerate(arrays):
                np.save(self._path(key, i), a, allow_pickle=False)
            self._spilled[key] = len(arrays)
            self.writes += 1

    def _drop(self, key: Hashable) -> None:
        self._resident.pop(key, None)
        for i in range(self._spilled.pop(key, 0)):
            self._path(key, i).unlink(missing_ok=True)

    def _path(self, key: Hashable, index: int) -> Path:
        if self._folder is None:
            self._folder = Path(tempfile.mkdtemp(prefix=f"vigs-{self.name}-", dir=self.config.directory or None))
            self._finalizer = weakref.finalize(self, shutil.rmtree, self._folder, True)
            fs = memory_backed(self._folder)
            if fs is not None:
                warnings.warn(f"{self.name}: spilled keyframes go to {self._folder}, on a {fs}, so they still "
                              f"take RAM; give the store's 'directory' (mapping.mapper.keyframe_store, "
                              f"loop.images) a folder on disk to bound memory", RuntimeWarning, stacklevel=2)
        return self._folder / f"{key}_{index}.npy"


_MEMORY_FILE_SYSTEMS = ("tmpfs", "ramfs")


def memory_backed(path: Path, mounts: list[tuple[str, str]] | None = None) -> str | None:
    """The file-system type when ``path`` lies on a memory-backed one (tmpfs, ramfs), else None: the type of the
    closest mount point above it. ``mounts``: ``(mount point, type)`` pairs (psutil's list of all mounts when
    None)."""
    if mounts is None:
        mounts = [(p.mountpoint, p.fstype) for p in psutil.disk_partitions(all=True)]
    resolved = Path(path).resolve()
    depth, found = -1, None
    for point, fs in mounts:   # in mount order: a later mount on the same point hides the earlier one
        point = Path(point)
        if (resolved == point or point in resolved.parents) and len(point.parts) >= depth:
            depth, found = len(point.parts), fs
    return found if found in _MEMORY_FILE_SYSTEMS else None
