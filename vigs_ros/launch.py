"""Launcher of the VIGS graph (``vigs launch``): the nodes as separate processes (default) or all in one
process (``composed``), optionally with a bag replay feeding them.

The nodes, their executables, parameter files and remaps come from the graph's ROS launch file
(``launch/vigs.launch.xml``, :mod:`vigs_ros.launch_file`), the one ``ros2 launch vigs_ros vigs.launch.xml`` runs.
Every node process gets ``--ros-args --params-file`` for its files there (``ros.yaml``, then the node's own) and
then the user's files (later files override earlier ones; each is checked first against the nodes' declared
parameters: unknown nodes or keys, wrong types and values out of range are errors,
:func:`vigs_ros.params.check_params_file`), its
remaps, and ``-p use_sim_time:=true`` when a bag is replayed (nodes run on the bag's ``/clock``). The composed
process gets the files and remaps of all its nodes.

Supervision: children run in their own sessions, so a terminal's Ctrl-C reaches only the launcher, which
forwards SIGINT/SIGTERM as SIGINT to every child (nodes close cleanly: the mapper saves its map), waits up to
``shutdown_timeout_s``, then escalates to SIGTERM and SIGKILL. When the replay finishes the graph gets
``linger_s`` to drain and is then shut down. Exit code: 0 after a clean shutdown; when a node exits on its own
(it died), the rest is shut down and the launcher returns that node's exit code (1 if it was 0 or a signal).
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from vigs_ros.graph import NODES, node_params
from vigs_ros.launch_file import LAUNCH_FILE, LaunchNode, read_launch_file
from vigs_ros.params import check_params_file


@dataclass
class LaunchConfig:
    """Args:
        bag: bag to replay into the graph (None: live topics).
        params: extra parameter files, applied after the shipped ones.
        composed: all nodes in one process with one MultiThreadedExecutor.
        nodes: nodes to start (default: all four).
        replay_args: extra ``vigs replay`` arguments (``--rate``, ``--fast``, ``--remap``...).
        ros_args: extra ``--ros-args`` items for every node (e.g. ``["-p", "torch_threads:=1"]``).
        linger_s: after the replay ends, time for the graph to drain before shutdown (s).
        shutdown_timeout_s: time a child gets to exit after SIGINT before SIGTERM / SIGKILL (s).
        launch_file: the graph's launch XML (nodes, parameter files, remaps).
    """

    bag: str | None = None
    params: list[str] = field(default_factory=list)
    composed: bool = False
    nodes: list[str] = field(default_factory=lambda: list(NODES))
    replay_args: list[str] = field(default_factory=list)
    ros_args: list[str] = field(default_factory=list)
    linger_s: float = 3.0
    shutdown_timeout_s: float = 30.0
    launch_file: Path = LAUNCH_FILE


def bag_input_remaps(bag: str | Path) -> tuple[list[str], list[str]]:
    """Remaps of a bag's sensor topics onto the nodes' default inputs, found by message type (the first topic
    of each type): an Image topic -> ``/image`` (else a CompressedImage topic -> ``/image`` with
    ``image_transport:=compressed`` for the frontend), CameraInfo -> ``/camera_info``, Imu -> ``/imu``.
    Returns ``(replay remaps "FROM:=TO", extra node --ros-args)``."""
    from vigs_core.io.rosbag import open_bag_reader

    reader = open_bag_reader(bag)
    try:
        by_type: dict[str, str] = {}
        for conn in sorted(reader.connections, key=lambda c: c.topic):
            by_type.setdefault(conn.msgtype, conn.topic)
    finally:
        reader.close()
    remaps, ros_args = [], []
    if "sensor_msgs/msg/Image" in by_type:
        remaps.append(f"{by_type['sensor_msgs/msg/Image']}:=/image")
    elif "sensor_msgs/msg/CompressedImage" in by_type:
        remaps.append(f"{by_type['sensor_msgs/msg/CompressedImage']}:=/image")
        ros_args += ["-p", "image_transport:=compressed"]
    for typename, topic in (("sensor_msgs/msg/CameraInfo", "/camera_info"), ("sensor_msgs/msg/Imu", "/imu")):
        if typename in by_type:
            remaps.append(f"{by_type[typename]}:={topic}")
    return remaps, ros_args


def launch_nodes(cfg: LaunchConfig) -> list[LaunchNode]:
    """The launch file's nodes that ``cfg`` starts, in its order; each must be a graph node run by its executable
    ``vigs_<name>``."""
    nodes = read_launch_file(cfg.launch_file)
    for node in nodes:
        if node.name not in NODES or node.exec != f"vigs_{node.name}":
            raise ValueError(f"launch file {cfg.launch_file}: node {node.name!r} with executable {node.exec!r}; "
                             f"expected one of {[f'vigs_{n}' for n in NODES]} named after it")
    missing = [n for n in cfg.nodes if n not in {node.name for node in nodes}]
    if missing:
        raise ValueError(f"unknown node(s) {missing}; the launch file {cfg.launch_file} has "
                         f"{[node.name for node in nodes]}")
    return [node for node in nodes if node.name in cfg.nodes]


def node_ros_args(cfg: LaunchConfig, nodes: list[LaunchNode]) -> list[str]:
    """``--ros-args`` of a process running ``nodes``: their parameter files (each once, in order), the user's,
    their remaps, sim time with a bag, and ``cfg.ros_args``."""
    files = list(dict.fromkeys([f for node in nodes for f in node.params] + [Path(f) for f in cfg.params]))
    specs = node_params()
    for f in files:
        if not f.is_file():
            raise ValueError(f"parameter file {f} does not exist")
        check_params_file(f, specs)
    args = ["--ros-args"]
    for f in files:
        args += ["--params-file", str(f)]
    for src, dst in dict.fromkeys(r for node in nodes for r in node.remaps):
        args += ["-r", f"{src}:={dst}"]
    if cfg.bag is not None:
        args += ["-p", "use_sim_time:=true"]
    return args + list(cfg.ros_args)


def commands(cfg: LaunchConfig) -> dict[str, list[str]]:
    """Child name -> command line (nodes, or one composed graph, then the replay)."""
    nodes = launch_nodes(cfg)
    py = sys.executable
    if cfg.composed:
        cmds = {"graph": [py, "-m", "vigs_ros.graph", *[n.name for n in nodes], *node_ros_args(cfg, nodes)]}
    else:
        cmds = {n.name: [py, "-m", NODES[n.name][0], *node_ros_args(cfg, [n])] for n in nodes}
    if cfg.bag is not None:
        cmds["replay"] = [py, "-m", "vigs_cli.main", "replay", str(cfg.bag), *cfg.replay_args]
    return cmds


class Supervisor:
    """Starts child processes, forwards signals, detects dead children, shuts everything down."""

    def __init__(self, shutdown_timeout_s: float = 30.0, linger_s: float = 3.0) -> None:
        self.procs: dict[str, subprocess.Popen] = {}
        self.shutdown_timeout_s = shutdown_timeout_s
        self.linger_s = linger_s
        self._signal: int | None = None

    def start(self, name: str, cmd: list[str]) -> None:
        proc = subprocess.Popen(cmd, start_new_session=True)
        self.procs[name] = proc
        print(f"[launch] started {name} (pid {proc.pid})", flush=True)

    def _on_signal(self, signum, frame) -> None:
        self._signal = signum

    def run(self) -> int:
        """Supervise until a signal, a dead node, or the end of the replay; returns the exit code."""
        old = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            return self._loop()
        finally:
            for s, h in old.items():
                signal.signal(s, h)

    def _loop(self) -> int:
        replay_done_at = None
        while True:
            if self._signal is not None:
                print(f"[launch] {signal.Signals(self._signal).name}: shutting down", flush=True)
                return self.shutdown()
            for name, proc in self.procs.items():
                rc = proc.poll()
                if rc is None:
                    continue
                if name == "replay":
                    if rc != 0:
                        print(f"[launch] replay failed (exit {rc}): shutting down", flush=True)
                        self.shutdown()
                        return rc
                    if replay_done_at is None:
                        replay_done_at = time.monotonic()
                        print(f"[launch] replay finished; shutting down in {self.linger_s:.1f} s", flush=True)
                    continue
                print(f"[launch] {name} exited unexpectedly with code {rc}: shutting down the graph", flush=True)
                self.shutdown()
                return rc if rc > 0 else 1
            if replay_done_at is not None and time.monotonic() - replay_done_at >= self.linger_s:
                return self.shutdown()
            time.sleep(0.05)

    def shutdown(self) -> int:
        """SIGINT every running child, escalate after the timeout; 0 if all exited with 0 (or were done)."""
        alive = {n: p for n, p in self.procs.items() if p.poll() is None}
        for p in alive.values():
            p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + self.shutdown_timeout_s
        for sig in (signal.SIGTERM, signal.SIGKILL):
            while time.monotonic() < deadline and any(p.poll() is None for p in alive.values()):
                time.sleep(0.05)
            stuck = [n for n, p in alive.items() if p.poll() is None]
            if not stuck:
                break
            print(f"[launch] {stuck} still running: sending {sig.name}", flush=True)
            for n in stuck:
                alive[n].send_signal(sig)
            deadline = time.monotonic() + 2.0
        for p in alive.values():
            p.wait()
        failed = {n: p.returncode for n, p in alive.items() if p.returncode != 0}
        if failed:
            print(f"[launch] unclean exit: {failed}", flush=True)
            return 1
        print("[launch] all processes exited cleanly", flush=True)
        return 0


def launch(cfg: LaunchConfig) -> int:
    """Start the graph of ``cfg`` and supervise it (blocking); the exit code."""
    cmds = commands(cfg)
    sup = Supervisor(cfg.shutdown_timeout_s, cfg.linger_s)
    try:
        for name, cmd in cmds.items():
            sup.start(name, cmd)
    except OSError as exc:
        print(f"[launch] cannot start: {exc}", flush=True)
        sup.shutdown()
        return 1
    return sup.run()
