"""The VIGS node graph: node names, their classes, and the composed process (all nodes, one executor)."""
from __future__ import annotations

import importlib
import sys

from vigs_ros.runtime import run_nodes

# node name -> (module, class); the order is the start order.
NODES = {
    "imu_preintegration": ("vigs_ros.imu_preintegration_node", "ImuPreintegrationNode"),
    "frontend": ("vigs_ros.frontend_node", "FrontendNode"),
    "mapper": ("vigs_ros.mapper_node", "MapperNode"),
    "loop_detector": ("vigs_ros.loop_detector_node", "LoopDetectorNode"),
}


def node_class(name: str):
    """The node class of graph node ``name``; ValueError for an unknown name."""
    if name not in NODES:
        raise ValueError(f"unknown node {name!r}; expected one of {list(NODES)}")
    module, cls = NODES[name]
    return getattr(importlib.import_module(module), cls)


def node_params(names: list[str] | None = None) -> dict[str, list]:
    """``{node name: its declared ParamSpecs}`` of the graph's nodes (default all)."""
    return {n: importlib.import_module(NODES[n][0]).PARAMS for n in (names or NODES)}


def main_composed(argv: list[str] | None = None) -> int:
    """``python -m vigs_ros.graph NODE... [--ros-args ...]``: the named nodes (default all) in this process,
    spun by one MultiThreadedExecutor."""
    argv = sys.argv[1:] if argv is None else argv
    split = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    names = argv[:split] or list(NODES)
    classes = [node_class(n) for n in names]
    return run_nodes(classes, ["vigs_graph", *argv[split:]], multithreaded=True)


if __name__ == "__main__":
    sys.exit(main_composed())
