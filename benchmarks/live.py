"""Live operation of the ROS 2 node graph (issue 17): camera rate, latency, skips, CPU, memory and accuracy.

Runs ``vigs launch --bag BAG`` (separate node processes; the replay publishes ``/clock`` and the sensor topics at
``--rate`` x real time, as a robot's drivers would, without waiting for the graph) while a probe node in this
process records the arrival time of every ``/image``, ``/imu``, ``/odometry`` and ``/vigs/imu_odometry`` message
and the last ``/vigs/status`` of every node. Per run:

* frames received by the probe, tracked / skipped (tracking behind) by the frontend and the images it never got
  (counted from the gaps in the stamps; its frontend_report.json);
* ``/odometry`` latency p50 / p95 / max: its arrival minus the arrival of the image with the same stamp, as a
  subscriber sees it (transport included; arrival = reception by the probe's DDS participant, the rmw's
  ``received_timestamp``, so that the probe's own Python scheduling does not count; the p95 by its callbacks is
  printed beside); the same for ``/vigs/imu_odometry`` against ``/imu``, and its rate (messages per second of bag
  time between its first and last message);
* CPU share (user + system over the run's wall time) and peak RSS per process (psutil, sampled every 0.2 s);
* the deepest frontend queues (IMU samples and frames waiting for the tracking thread);
* keyframes the mapper received, mapped (steps per keyframe, how many cut short) and deferred, its idle steps, and
  the events it had pending at its last status and at most over the run;
* the IMU initialisation's stamp (s after the first frame); SE(3) ATE of the live ``trajectory.txt`` and of the
  recorded ``/odometry`` after the IMU initialisation, against the ground truth beside the bag.

Then the same bag ``--fast`` (the replay waits for the frontend, nothing is skipped) for comparison.
``--starve N`` runs N busy processes beside the graph (a saturated robot computer).
``--variant NAME=FILE`` adds a live run with that parameter file (settings compared in one invocation).
Run: ``vigs bench live [--bag BAG ...] [--rate 1] [--starve 0] [--no-fast] [--variant NAME=FILE ...]`` (default
bag: the shipped sample).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from vigs_ros.launch import bag_input_remaps

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "bags" / "v1_01_easy_hybrid_376x240"
# process name -> what its command line contains
PROCESS_KEYS = [(n, f"vigs_ros.{n}_node") for n in ("imu_preintegration", "frontend", "mapper", "loop_detector")]
PROCESS_KEYS += [("replay", "vigs_cli.main replay")]


class Probe:
    """Arrival times (monotonic s) by stamp of the graph's inputs and outputs; odometry poses; last statuses."""

    def __init__(self, domain_id: int, compressed: bool) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import CompressedImage, Image, Imu

        from vigs_ros.qos import latched_qos, reliable_qos, sensor_qos
        from vigs_ros.runtime import ThreadedSubscription

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("live_probe", context=self.ctx)
        keys = ("image", "imu", "odom", "imu_odom")
        self.at: dict[str, dict[tuple[int, int], float]] = {k: {} for k in keys}   # callback, monotonic s
        self.rx: dict[str, dict[tuple[int, int], float]] = {k: {} for k in keys}   # reception by DDS, s
        self.odometry = []
        self.status: dict[str, dict[str, str]] = {}
        self.mapper_pending_max = 0

        def record(key, stamp, info):
            self.at[key].setdefault(stamp, time.monotonic())
            self.rx[key].setdefault(stamp, info["received_timestamp"] * 1e-9)

        def stamps_of(key):
            """Callback of a raw threaded subscription: each stamp is read from the serialized header (CDR: 4 bytes
            of encapsulation, then int32 sec, uint32 nanosec), so the probe neither deserialises an image or a
            200 Hz message nor pays the executor's cost per message: its own CPU stays small beside the graph
            it measures."""
            def on_messages(taken):
                for raw, info in taken:
                    record(key, struct.unpack_from("<iI", raw, 4), info)
            return on_messages

        def on_odom(m, info):
            record("odom", (m.header.stamp.sec, m.header.stamp.nanosec), info)
            self.odometry.append(m)

        def on_status(m):
            for st in m.status:
                self.status[st.name] = {kv.key: kv.value for kv in st.values}
                if st.name.endswith("mapper") and "pending_events" in self.status[st.name]:
                    pending = int(self.status[st.name]["pending_events"])
                    self.mapper_pending_max = max(self.mapper_pending_max, pending)

        self.readers = [ThreadedSubscription(self.node, msg_type, topic, stamps_of(key), qos, raw=True, with_info=True)
                        for msg_type, topic, key, qos in (
                            (CompressedImage if compressed else Image, "/image", "image", sensor_qos(100)),
                            (Imu, "/imu", "imu", sensor_qos(1000)),
                            (Odometry, "/vigs/imu_odometry", "imu_odom", reliable_qos(1000)))]
        sub = self.node.create_subscription
        sub(Odometry, "/odometry", on_odom, reliable_qos(1000))
        sub(DiagnosticArray, "/vigs/status", on_status, latched_qos(10))
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self.stop.is_set():
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        for reader in self.readers:
            reader.stop()
        self.node.destroy_node()
        self.ctx.try_shutdown()

    def latencies(self, out: str, inp: str, received: bool = True) -> list[tuple[int, float]]:
        """(stamp ns, arrival of ``out`` minus arrival of ``inp`` in ms) for every stamp both have, in stamp order:
        arrival = reception by the probe's DDS participant (``received``, what any subscriber gets, free of this
        process's own scheduling) or the probe's Python callback."""
        a, b = (self.rx[out], self.rx[inp]) if received else (self.at[out], self.at[inp])
        return sorted((k[0] * 10**9 + k[1], 1e3 * (a[k] - b[k])) for k in a if k in b)

    def latency_ms(self, out: str, inp: str, received: bool = True) -> np.ndarray:
        """The latencies (ms) of :meth:`latencies`."""
        return np.array([ms for _, ms in self.latencies(out, inp, received)])


def busy_processes(n: int) -> list[subprocess.Popen]:
    """``n`` processes that spin on a CPU core until killed (each in a session of its own: an ordinary
    competitor, not sharing the probe's priority)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True) for _ in range(n)]


PROBE_NICE = -10


def prioritise_probe(argv: list[str]) -> int | None:
    """Give the probe (this process) the priority of a controller consuming odometry, so that its own scheduling
    does not count in the latencies: the benchmark leads a session of its own (re-run as one when it was started
    as a process group leader, as an interactive shell does) and sets that session's autogroup niceness to
    ``PROBE_NICE`` (root or CAP_SYS_NICE; otherwise it says so and goes on). The nodes start in sessions of their
    own at their configured priority. Returns the exit code of the re-run, or None to go on here."""
    from vigs_ros.runtime import renice

    if os.getsid(0) != os.getpid():
        try:
            os.setsid()
        except PermissionError:   # a process group leader: re-run as the leader of a new session
            child = subprocess.Popen([sys.executable, "-m", "vigs_cli.main", "bench", "live", *argv],
                                     start_new_session=True)
            try:
                return child.wait()
            except KeyboardInterrupt:
                child.send_signal(signal.SIGINT)
                return child.wait()
    if not renice(PROBE_NICE, threads=False):
        print(f"probe at normal priority (niceness {PROBE_NICE} needs root or CAP_SYS_NICE): its own scheduling "
              f"counts in the latencies")
    return None


def run_graph(bag: Path, out: Path, pace: list[str], env: dict, compressed: bool, starve: int,
              extra_params: list[str]) -> dict:
    import psutil

    out.mkdir(parents=True, exist_ok=True)
    params = out / "params.yaml"
    params.write_text(f"frontend:\n  ros__parameters:\n    output_dir: {out}\n"
                      f"mapper:\n  ros__parameters:\n    map_path: {out / 'map.ply'}\n")
    probe = Probe(int(env["ROS_DOMAIN_ID"]), compressed)
    busy = busy_processes(starve)
    # the replay starts once /image and /imu have a subscriber: the probe is one, so give the node processes
    # time to start and match before the first message (else the frontend misses the first seconds)
    cmd = [sys.executable, "-m", "vigs_cli.main", "launch", "--bag", str(bag), "--params", str(params),
           *(x for f in extra_params for x in ("--params", f)), "--linger", "5", "--settle", "8", *pace]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    launcher = psutil.Process(proc.pid)
    me = psutil.Process()
    own = me.cpu_times()
    cpu: dict[str, float] = {}
    rss: dict[str, float] = {}
    names: dict[int, str] = {}
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    try:
        while proc.poll() is None:  # sample children's CPU times and memory until they exit
            for child in launcher.children(recursive=True):
                try:
                    # a child seen between its fork and its exec still shows the launcher's command line: name it
                    # only once it matches
                    name = names.get(child.pid) or next((n for n, key in PROCESS_KEYS
                                                         if key in " ".join(child.cmdline())), None)
                    if name is None:
                        continue
                    names[child.pid] = name
                    t = child.cpu_times()
                    cpu[name] = max(cpu.get(name, 0.0), t.user + t.system)
                    rss[name] = max(rss.get(name, 0.0), child.memory_info().rss / 2**20)
                except psutil.Error:
                    pass
            time.sleep(0.2)
    finally:
        for b in busy:
            b.kill()
            b.wait()
    wall = time.monotonic() - t0
    now = me.cpu_times()
    cpu["probe (this process)"] = now.user + now.system - own.user - own.system
    reader.join(5)
    time.sleep(0.5)
    probe.close()
    (out / "launch.log").write_text("".join(lines))   # the nodes' shutdown reports, kept with --keep
    report_path = out / "frontend_report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    return {"rc": proc.returncode, "wall_s": wall, "probe": probe, "cpu_s": cpu, "rss_mb": rss,
            "report": report, "log": "".join(lines), "out": out}


def odometry_ate_after_init(probe: Probe, gt, init_s: float | None) -> float:
    """SE(3) ATE (m) of the recorded ``/odometry`` poses stamped after the IMU initialisation."""
    from msg_adapters.odometry import odometry_to_pose
    from vigs_core.eval import evaluate_trajectory
    from vigs_core.system.pipeline import poses_to_trajectory

    if init_s is None:
        return float("nan")
    poses = [odometry_to_pose(m) for m in probe.odometry]
    poses = sorted((p for p in poses if p["t_ns"] > init_s * 1e9), key=lambda p: p["t_ns"])
    if len(poses) < 10:
        return float("nan")
    est = poses_to_trajectory(np.array([p["t_ns"] for p in poses]), np.stack([p["T"] for p in poses]))
    try:
        return float(evaluate_trajectory(gt, est, align="se3", max_diff_s=1e-3)["ate_rmse"])
    except ValueError:
        return float("nan")


def summarize(r: dict, gt) -> dict:
    """The table's figures of one run."""
    from vigs_core.eval import evaluate_trajectory
    from vigs_core.io import read_tum

    probe, rep = r["probe"], r["report"]
    imu_t = sorted(probe.at["imu_odom"])
    imu_span = (imu_t[-1][0] + imu_t[-1][1] * 1e-9) - (imu_t[0][0] + imu_t[0][1] * 1e-9) if len(imu_t) > 1 else 0
    first_image = min(probe.at["image"]) if probe.at["image"] else None
    init_s = rep.get("inertial_initialized_at_s")
    traj = r["out"] / "trajectory.txt"
    ate = float("nan")
    if traj.is_file() and init_s is not None:
        try:
            ate = float(evaluate_trajectory(gt, read_tum(traj), align="se3", max_diff_s=1e-3)["ate_rmse"])
        except ValueError:
            pass
    mapper, imu_node = (next((v for k, v in probe.status.items() if k.endswith(node)), {})
                        for node in ("mapper", "imu_preintegration"))
    pct = lambda x, q: float(np.percentile(x, q)) if len(x) else float("nan")  # noqa: E731
    lat, ilat = probe.latency_ms("odom", "image"), probe.latency_ms("imu_odom", "imu")
    return {
        "images": len(probe.at["image"]), "tracked": rep.get("frames_tracked"), "skipped": rep.get("frames_skipped"),
        "lost": rep.get("frames_lost_before_node"),
        "odometry": len(probe.at["odom"]), "lat_p50": pct(lat, 50), "lat_p95": pct(lat, 95),
        "lat_max": float(lat.max()) if len(lat) else float("nan"),
        "imu_odom_hz": (len(imu_t) - 1) / imu_span if imu_span > 0 else 0.0,
        "imu_lat_p95": pct(ilat, 95), "imu_lat_max": float(ilat.max()) if len(ilat) else float("nan"),
        "lat_p95_callback": pct(probe.latency_ms("odom", "image", received=False), 95),
        "imu_lat_p95_callback": pct(probe.latency_ms("imu_odom", "imu", received=False), 95),
        "init_s": None if init_s is None or first_image is None else init_s - (first_image[0] + first_image[1] * 1e-9),
        "ate_traj": ate, "ate_odom": odometry_ate_after_init(probe, gt, init_s),
        "queue_max": rep.get("queue_max"), "mapper_kf": mapper.get("keyframes_in"),
        "mapper_pending": mapper.get("pending_events"), "mapper_pending_max": probe.mapper_pending_max,
        "mapper_mapped": mapper.get("keyframes_mapped"), "mapper_idle_steps": mapper.get("idle_steps"),
        "mapper_steps_per_kf": mapper.get("steps_per_keyframe"), "mapper_cut_short": mapper.get("keyframes_cut_short"),
        "mapper_deferred": mapper.get("keyframes_deferred"),
        "node_lat": (rep.get("odometry_latency_ms") or {}).get("p95"),
        "node_wait": (rep.get("tracking_wait_ms") or {}).get("p95"),
        "imu_node_lat": imu_node.get("odometry_latency_ms"),
        "wall_s": r["wall_s"],
        "cpu": {k: 100 * v / r["wall_s"] for k, v in sorted(r["cpu_s"].items())},
        "rss": dict(sorted(r["rss_mb"].items())),
    }


def main(argv: list[str] | None = None) -> int:
    from vigs_core.system.sources import open_input

    parser = argparse.ArgumentParser(prog="vigs bench live", description=__doc__.splitlines()[0])
    parser.add_argument("--bag", action="append", help="bag(s) to replay, with ground truth beside "
                                                       "(default: the shipped sample)")
    parser.add_argument("--rate", type=float, default=1.0, help="replay rate of the live run")
    parser.add_argument("--starve", type=int, default=0, help="busy processes beside the graph")
    parser.add_argument("--no-fast", action="store_true", help="skip the --fast comparison run")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME=FILE",
                        help="also run the live run with this parameter file (repeatable): settings compared in "
                             "one invocation, each bag's runs one after the other")
    parser.add_argument("--keep", help="keep the runs' outputs in this folder")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args(argv)
    rerun = prioritise_probe(sys.argv[1:] if argv is None else argv)
    if rerun is not None:
        return rerun
    variants = [v.split("=", 1) for v in args.variant]
    if any(len(v) != 2 or not Path(v[1]).is_file() for v in variants):
        parser.error("--variant takes NAME=FILE with an existing parameter file")
    env = dict(os.environ, ROS_DOMAIN_ID=str(10 + os.getpid() % 91), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(args.keep or tmp)
        for bag in map(Path, args.bag or [SAMPLE]):
            gt = open_input(bag).groundtruth
            if gt is None:
                print(f"{bag}: no ground truth beside the bag")
                return 2
            compressed = "image_transport:=compressed" in bag_input_remaps(bag)[1]
            live = ["--rate", str(args.rate)]
            runs = [(f"x{args.rate:g}", live, args.starve, [])]
            runs += [(f"x{args.rate:g} {name}", live, args.starve, [file]) for name, file in variants]
            runs += [] if args.no_fast else [("fast", ["--fast"], 0, [])]
            for label, pace, starve, extra in runs:
                r = run_graph(bag, base / f"{bag.name}_{label.replace(' ', '_')}", pace, env, compressed, starve,
                              extra)
                if r["rc"] != 0:
                    print(r["log"][-4000:])
                    print(f"{bag.name} {label}: the graph exited with code {r['rc']}")
                    return 1
                rows.append((bag.name, label + (f" starve {starve}" if starve else ""), summarize(r, gt)))
                (r["out"] / "latency.json").write_text(json.dumps({   # per message: when the tail happens
                    "odometry": r["probe"].latencies("odom", "image"),
                    "imu_odometry": r["probe"].latencies("imu_odom", "imu")}))
    print(f"load average before the last run: {os.getloadavg()[0]:.2f}")
    head = (f"{'bag':<28} {'run':<13} {'images':>6} {'tracked':>7} {'skipped':>7} {'odom':>5} {'lat p50':>7} "
            f"{'p95':>6} {'max':>6} {'imu Hz':>6} {'imu p95':>7} {'imu max':>7} {'init s':>6} {'ATE traj':>8} "
            f"{'ATE odom':>8}")
    print(head)
    for name, label, f in rows:
        init = "-" if f["init_s"] is None else f"{f['init_s']:.2f}"
        print(f"{name[:28]:<28} {label:<13} {f['images']:>6} {f['tracked']!s:>7} {f['skipped']!s:>7} "
              f"{f['odometry']:>5} {f['lat_p50']:>7.1f} {f['lat_p95']:>6.1f} {f['lat_max']:>6.0f} "
              f"{f['imu_odom_hz']:>6.1f} {f['imu_lat_p95']:>7.2f} {f['imu_lat_max']:>7.1f} {init:>6} "
              f"{100 * f['ate_traj']:>6.2f}cm {100 * f['ate_odom']:>6.2f}cm")
    print("latencies in ms (image or IMU arrival to odometry arrival, by the probe's DDS reception stamps)")
    for name, label, f in rows:
        cpu = ", ".join(f"{k} {v:.0f}% {f['rss'].get(k, 0):.0f} MB" for k, v in f["cpu"].items())
        print(f"{name[:28]:<28} {label:<13} wall {f['wall_s']:.0f} s; CPU of one core and peak RSS: {cpu}; "
              f"p95 by the probe's callbacks: odometry {f['lat_p95_callback']:.1f}, IMU odometry "
              f"{f['imu_lat_p95_callback']:.2f} ms; inside the nodes: odometry p95 {f['node_lat']} ms (frontend: "
              f"callback to publish; callback to tracking start p95 {f['node_wait']} ms), IMU odometry "
              f"{f['imu_node_lat']}; deepest queues {f['queue_max']}; images lost before the "
              f"frontend {f['lost']}; mapper keyframes "
              f"{f['mapper_kf']}, mapped {f['mapper_mapped']} ({f['mapper_steps_per_kf']} steps each, "
              f"{f['mapper_cut_short']} cut short), deferred {f['mapper_deferred']}, idle steps "
              f"{f['mapper_idle_steps']}, pending "
              f"{f['mapper_pending']} at the last status (at most {f['mapper_pending_max']})")
    if args.json:
        Path(args.json).write_text(json.dumps([{"bag": n, "run": l, **f} for n, l, f in rows], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
