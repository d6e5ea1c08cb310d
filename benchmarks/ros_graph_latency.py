"""End-to-end latency and CPU of the ROS 2 node graph replaying a bag (issue 7's benchmark).

Runs ``vigs launch --bag BAG`` (separate node processes, replay at ``--rate``), while a probe node in this
process records the arrival time of every ``/image`` and every ``/odometry`` message: latency is odometry
arrival minus arrival of the image with the same stamp (image stamp to odometry publish, as a subscriber
sees it, transport included). CPU per process from psutil over the run. Then the same bag ``--fast`` (as
fast as the frontend consumes) gives the sustained frame rate.

Without ``--bag`` a procedural simulated bag is rendered first (``vigs sim``, 376x240, ``--duration`` s); the
frontend processes ``--width`` x ``--height`` (default 376x240, the default processing size of EuRoC's
752x480). Run: ``vigs bench ros_graph_latency [--bag BAG] [--rate 1] [--duration 8] [--width 188 --height 120]``.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from vigs_ros.launch import bag_input_remaps

ROOT = Path(__file__).resolve().parent.parent
# process name -> what its command line contains
PROCESS_KEYS = [(n, f"vigs_ros.{n}_node") for n in ("imu_preintegration", "frontend", "mapper", "loop_detector")]
PROCESS_KEYS += [("replay", "vigs_cli.main replay")]


def render_bag(out: Path, duration: float) -> Path:
    bag = out / "sim_bag"
    cmd = [sys.executable, "-m", "vigs_cli.main", "sim", "--procedural", "--procedural-duration", str(duration + 2),
           "--duration", str(duration), "--width", "376", "--noise-free-imu", "--bag", str(bag)]
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return bag


def run_graph(bag: Path, params: Path, pace: list[str], env: dict, compressed: bool) -> dict:
    import psutil
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import CompressedImage, Image

    from vigs_ros.qos import reliable_qos, sensor_qos

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
    node = Node("latency_probe", context=ctx)
    image_at, odom_at = {}, {}
    node.create_subscription(CompressedImage if compressed else Image, "/image", lambda m: image_at.setdefault(
        (m.header.stamp.sec, m.header.stamp.nanosec), time.monotonic()), sensor_qos(100))
    node.create_subscription(Odometry, "/odometry", lambda m: odom_at.setdefault(
        (m.header.stamp.sec, m.header.stamp.nanosec), time.monotonic()), reliable_qos(1000))
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=0.01) for _ in iter(stop.is_set, True)])
    spinner.start()
    cmd = [sys.executable, "-m", "vigs_cli.main", "launch", "--bag", str(bag), "--params", str(params),
           "--linger", "5", *pace]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    launcher = psutil.Process(proc.pid)
    cpu: dict[str, float] = {}
    names: dict[int, str] = {}
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    while proc.poll() is None:  # sample children's CPU times until they exit
        for child in launcher.children(recursive=True):
            try:
                cmdline = " ".join(child.cmdline())
                name = names.setdefault(child.pid, next((n for n, key in PROCESS_KEYS if key in cmdline), "other"))
                t = child.cpu_times()
                cpu[name] = max(cpu.get(name, 0.0), t.user + t.system)
            except psutil.Error:
                pass
        time.sleep(0.2)
    wall = time.monotonic() - t0
    reader.join(5)
    stop.set()
    spinner.join(5)
    node.destroy_node()
    ctx.try_shutdown()
    lat = np.array([odom_at[k] - image_at[k] for k in odom_at if k in image_at]) * 1e3
    return {"rc": proc.returncode, "wall_s": wall, "images": len(image_at), "odometry": len(odom_at),
            "latency_ms": lat, "cpu_s": cpu, "log": "".join(lines)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="vigs bench ros_graph_latency", description=__doc__.splitlines()[0])
    parser.add_argument("--bag", help="bag to replay (default: render a procedural one)")
    parser.add_argument("--rate", type=float, default=1.0, help="replay rate of the latency run")
    parser.add_argument("--duration", type=float, default=8.0, help="length of the rendered bag (s)")
    parser.add_argument("--width", type=int, default=376, help="frontend processing width (px)")
    parser.add_argument("--height", type=int, default=240, help="frontend processing height (px)")
    parser.add_argument("--no-fast", action="store_true", help="skip the --fast (sustained rate) run")
    args = parser.parse_args(argv)
    env = dict(os.environ, ROS_DOMAIN_ID=str(10 + os.getpid() % 91), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bag = Path(args.bag) if args.bag else render_bag(tmp, args.duration)
        compressed = "image_transport:=compressed" in bag_input_remaps(bag)[1]
        params = tmp / "bench.yaml"
        params.write_text(f"frontend:\n  ros__parameters:\n    width: {args.width}\n    height: {args.height}\n"
                          f"mapper:\n  ros__parameters:\n    map_path: {tmp / 'map.ply'}\n")
        rows = []
        runs = [(f"x{args.rate:g}", ["--rate", str(args.rate)])] + ([] if args.no_fast else [("fast", ["--fast"])])
        for label, pace in runs:
            r = run_graph(bag, params, pace, env, compressed)
            if r["rc"] != 0:
                print(r["log"])
                print(f"graph run {label} failed with exit code {r['rc']}")
                return 1
            rows.append((label, r))
    print(f"bag: {args.bag or f'procedural sim, 376x240, {args.duration:g} s'}; frontend processing "
          f"{args.width}x{args.height}")
    print(f"{'run':>6} {'images':>7} {'odom':>6} {'lat p50 ms':>11} {'lat p95 ms':>11} {'wall s':>7} "
          f"{'frames/s':>9}  CPU s (% of one core over the run) per process")
    for label, r in rows:
        lat = r["latency_ms"]
        # latency is meaningful when images arrive at their recorded rate, not when replay waits for the graph
        p50, p95 = (np.percentile(lat, 50), np.percentile(lat, 95)) if len(lat) and label != "fast" else (
            float("nan"),) * 2
        cpu = ", ".join(f"{k} {v:.1f} ({100 * v / r['wall_s']:.0f}%)" for k, v in sorted(r["cpu_s"].items()))
        print(f"{label:>6} {r['images']:>7} {r['odometry']:>6} {p50:>11.1f} {p95:>11.1f} {r['wall_s']:>7.1f} "
              f"{r['images'] / r['wall_s']:>9.1f}  {cpu}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
