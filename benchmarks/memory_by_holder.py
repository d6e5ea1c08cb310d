"""Where a long run's memory goes (issue 19): live bytes per holder of ``vigs run``'s main process at two frame
counts, per keyframe added between them.

Runs the pipeline in this process on BAG (``--params`` as ``vigs run``) and, when the frame count reaches each of
``--at`` (default 1200 and 3000), walks the objects each holder reaches (tensor storages and NumPy buffers once
each, plus containers and object dictionaries; a part shared by two holders counts for the first) and reads the
process RSS and glibc's allocated bytes (``mallinfo2``). Prints, per holder, the size at both counts and the
growth per keyframe; RSS growth beyond the holders' is the allocator's (fragmentation) or unlisted holders'.
The loop-closure and mapping children are separate processes (``mapping: {process: false}`` and
``loop: {process: false}`` in ``--params`` put the mapper's and the loop closure's holders here): ``vigs bench
soak`` gives their RSS.

    vigs bench memory_by_holder BAG [--at 1200,3000] [--params FILE]
"""
from __future__ import annotations

import argparse
import ctypes
import gc
import sys
import tempfile
from typing import Any

import numpy as np
import psutil
import torch

TENSOR_OVERHEAD = 300   # bytes of a tensor's Python object, TensorImpl and StorageImpl (approximate)


def reachable_bytes(obj: Any, seen: set) -> int:
    """Bytes of ``obj`` and what it reaches that is not in ``seen`` (updated)."""
    total, stack = 0, [obj]
    while stack:
        o = stack.pop()
        if id(o) in seen or isinstance(o, (type, type(sys))) or (callable(o) and not hasattr(o, "__dict__")):
            continue
        seen.add(id(o))
        if isinstance(o, torch.Tensor):
            storage = o.untyped_storage()
            total += TENSOR_OVERHEAD
            if ("storage", storage.data_ptr()) not in seen and storage.data_ptr():
                seen.add(("storage", storage.data_ptr()))
                total += storage.nbytes()
            continue
        if isinstance(o, np.ndarray):
            base = o
            while isinstance(base.base, np.ndarray):
                base = base.base
            total += sys.getsizeof(np.empty(0))
            if ("array", id(base)) not in seen and base.base is None:
                seen.add(("array", id(base)))
                total += base.nbytes
            continue
        total += sys.getsizeof(o)
        if isinstance(o, dict):
            stack += [*o.keys(), *o.values()]
        elif isinstance(o, (list, tuple, set, frozenset)) or type(o).__name__ == "deque":
            stack += list(o)
        elif hasattr(o, "__dict__") and not isinstance(o, (str, bytes, int, float)):
            stack.append(o.__dict__)
        elif not isinstance(o, (str, bytes, int, float)):   # a __slots__ class: what its slots hold
            slots = [n for c in type(o).__mro__ for n in getattr(c, "__slots__", ())]
            stack += [getattr(o, n) for n in slots if hasattr(o, n)]
    return total


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                      "fsmblks", "uordblks", "fordblks", "keepcost")]


def malloc_in_use() -> int | None:
    """Bytes glibc's malloc has handed out and not got back (all arenas and mapped blocks); None elsewhere."""
    try:
        mallinfo2 = ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return None
    mallinfo2.restype = _MallInfo2
    info = mallinfo2()
    return int(info.uordblks + info.hblkhd)


def holders(odo: Any, mapping: Any) -> dict[str, Any]:
    """The long-lived holders of the main process, in counting order."""
    from vigs_core.loop.closure import LoopClosure
    from vigs_core.loop.driver import LoopClosureDriver
    from vigs_core.mapping.mapper import GaussianMapper

    out = {"odometry frames": odo.frames, "odometry keyframes": odo.keyframes,
           "visual-inertial state": getattr(odo, "vio", None), "frame status": getattr(odo, "frame_status", None)}
    if mapping is not None:
        m = mapping.mapper
        if isinstance(m, GaussianMapper):   # a mapper thread (mapping.process false); else it is the child's
            out |= {"mapper keyframes (+ store)": m.keyframes, "Gaussian map": m.map, "mapper optimiser": m.optimizer}
        out["mapping bookkeeping"] = mapping
    drivers = [o for o in gc.get_objects() if isinstance(o, LoopClosureDriver)]
    if drivers:
        out["loop-closure views"] = drivers[0]._views
        closure = drivers[0].closure
        if isinstance(closure, LoopClosure):   # a loop-closure thread (loop.process false); else the child's
            out |= {"loop detector (thumbnails, kept images)": closure.detector, "loop pose graph": closure.graph,
                    "loop decisions": closure.decisions}
        out["loop-closure caller"] = drivers[0]
    out["odometry (rest)"] = odo
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vigs bench memory_by_holder", description=__doc__.split("\n\n")[0])
    p.add_argument("bag", help="a recording vigs run reads (ROS bag or EuRoC folder)")
    p.add_argument("--at", default="1200,3000", help="the two frame counts to measure at")
    p.add_argument("--params", help="vigs run's --params")
    args = p.parse_args(argv)
    from vigs_core.system import load_config, pipeline

    at = [int(a) for a in args.at.split(",")]
    snapshots: dict[int, dict] = {}
    step = pipeline.Checkpoints.step

    def measuring_step(self, odo, T_BS, frames, mapping):   # called once per frame by run_pipeline
        if frames in at and frames not in snapshots:
            gc.collect()
            seen: set = set()
            sizes = {name: reachable_bytes(obj, seen) for name, obj in holders(odo, mapping).items()}
            snapshots[frames] = {"keyframes": len(odo.keyframes), "rss": psutil.Process().memory_info().rss,
                                 "malloc": malloc_in_use(),
                                 "gaussians": mapping.mapper.summary().gaussians if mapping is not None else 0,
                                 "sizes": sizes}
        return step(self, odo, T_BS, frames, mapping)

    pipeline.Checkpoints.step = measuring_step
    cfg = load_config(args.params)
    cfg.max_frames = max(at) + 2
    with tempfile.TemporaryDirectory() as out:
        pipeline.run_pipeline(args.bag, cfg, out, progress=False)
    if len(snapshots) < 2:
        print(f"the run ended before frame {max(at)}")
        return 1
    a, b = snapshots[at[0]], snapshots[at[-1]]
    dk = b["keyframes"] - a["keyframes"]
    print(f"\nframes {at[0]} -> {at[-1]}: keyframes {a['keyframes']} -> {b['keyframes']}, Gaussians "
          f"{a['gaussians']} -> {b['gaussians']}")
    print(f"{'holder':>28} {'MB at ' + str(at[0]):>12} {'MB at ' + str(at[-1]):>12} {'KB/keyframe':>12}")
    rows = [(name, a["sizes"][name], b["sizes"][name]) for name in a["sizes"]]
    rows += [("(process RSS)", a["rss"], b["rss"])]
    rows += [("(malloc in use)", a["malloc"], b["malloc"])] if a["malloc"] is not None else []
    for name, x, y in rows:
        print(f"{name:>28} {x / 2**20:12.2f} {y / 2**20:12.2f} {(y - x) / 1024 / max(dk, 1):12.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
