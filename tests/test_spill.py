"""The keyframe spill store: bounded resident entries, exact read-back, its folder removed on close."""
import numpy as np
import pytest

from vigs_core.spill import SpillConfig, SpillStore


def _entry(k: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(k)
    return rng.integers(0, 255, (12, 16, 3), dtype=np.uint8), rng.random((12, 16), dtype=np.float32)


def test_old_entries_leave_memory_and_come_back_identical(tmp_path):
    store = SpillStore(SpillConfig(resident=3, directory=str(tmp_path)), "test")
    for k in range(10):
        store.put(k, *_entry(k))
    assert len(store) == 10 and store.resident_count == 3 and store.writes == 7
    assert len(list(tmp_path.rglob("*.npy"))) == 14      # two arrays each for the seven spilled entries
    for k in (0, 9, 4):
        got = store.get(k)
        assert all(np.array_equal(a, b) and a.dtype == b.dtype for a, b in zip(got, _entry(k)))
    assert store.reads == 2 and store.resident_count == 3    # 9 was resident; reading spills the oldest again
    with pytest.raises(KeyError):
        store.get(42)


def test_replacing_and_discarding_remove_the_spilled_files_and_close_removes_the_folder(tmp_path):
    store = SpillStore(SpillConfig(resident=1, directory=str(tmp_path)), "test")
    store.put("a", np.zeros(4))
    store.put("b", np.ones(4))                                   # spills "a"
    store.put("a", np.full(4, 2.0))                              # replaces the spilled "a" (spills "b")
    assert np.array_equal(store.get("a")[0], np.full(4, 2.0)) and np.array_equal(store.get("b")[0], np.ones(4))
    store.discard("a")
    assert "a" not in store and len(store) == 1
    folders = list(tmp_path.iterdir())   # "b" is resident, "a" gone: no files left
    assert len(folders) == 1 and list(folders[0].iterdir()) == []
    store.close()
    assert list(tmp_path.iterdir()) == [] and len(store) == 0


def test_resident_zero_keeps_everything_in_memory(tmp_path):
    store = SpillStore(SpillConfig(resident=0, directory=str(tmp_path)), "test")
    for k in range(5):
        store.put(k, *_entry(k))
    assert store.resident_count == 5 and store.writes == 0 and list(tmp_path.iterdir()) == []


MOUNTS = [("/", "ext4"), ("/tmp", "tmpfs"), ("/tmp/disk", "ext4"), ("/run/ram", "ramfs")]


def test_a_memory_backed_spill_folder_is_recognised_by_its_closest_mount():
    from pathlib import Path

    from vigs_core.spill import memory_backed

    assert memory_backed(Path("/tmp/vigs-x"), MOUNTS) == "tmpfs"
    assert memory_backed(Path("/tmp/disk/vigs-x"), MOUNTS) is None      # a disk mounted inside the tmpfs
    assert memory_backed(Path("/run/ram/a/b"), MOUNTS) == "ramfs"
    assert memory_backed(Path("/var/cache/vigs"), MOUNTS) is None
    assert memory_backed(Path("/tmpfoo/x"), MOUNTS) is None               # a prefix of the name is not a parent


def test_a_store_that_spills_into_ram_warns_once(tmp_path, monkeypatch):
    import vigs_core.spill as spill

    monkeypatch.setattr(spill, "memory_backed", lambda path, mounts=None: "tmpfs")
    store = SpillStore(SpillConfig(resident=1, directory=str(tmp_path)), "test")
    with pytest.warns(RuntimeWarning, match="on a tmpfs") as caught:
        for k in range(4):
            store.put(k, *_entry(k))
    assert len(caught) == 1
    store.close()
