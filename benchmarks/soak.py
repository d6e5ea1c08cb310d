"""Memory over a long run (issue 19): RSS of every process sampled while ``vigs run`` and the graph work through a
long procedural sequence.

The sequence is ``vigs sim --procedural --procedural-duration D`` (procedural motion with synthesised IMU inside
one room, so the scene is revisited), written once as a ROS 2 bag into ``--cache``. Then, each with mapping and
loop closure on:

* ``vigs run BAG`` (one process plus its loop-closure and mapping children);
* ``vigs launch --bag BAG --fast`` (the node processes; the replay waits for the frontend), or with
  ``--realtime`` at the recorded rate, as a robot's sensors give it: its MB per minute of wall time is then per
  minute of the mission.

Every ``--sample-s`` seconds the RSS of the run's processes (by role: the run or its node name, the loop-closure
and mapping workers by their process names) and the frontend's keyframe count (from the progress of ``vigs run``;
the graph's is not sampled) are recorded. Printed per process: peak RSS, RSS at the end of the warm-up
(``--warmup-s`` of wall time) and at the end (the last two samples, which can catch a process exiting, are left
out), the slope after the warm-up (least squares, MB per minute of wall time; for ``vigs run`` only while it
tracks, before the first sample at the final keyframe count, not while the mapper drains or the loop-closure child
exits), and for ``vigs run`` the slope per keyframe; then the output sizes. The run folders are removed after
that unless ``--keep`` (the rendered bag stays in the cache).

    vigs bench soak [--duration 1800] [--warmup-s 300] [--sample-s 10] [--cache out/soak] [--no-graph | --no-run]
                    [--realtime] [--params FILE] [--bag BAG] [--json OUT] [--keep]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
NAMES = {"vigs-loop": "loop-closure", "vigs-mapper": "mapper-process"}   # process names of vigs run's children
ROLES = (("imu_preintegration", "imu_preintegration_node"),
         ("frontend", "frontend_node"), ("mapper", "mapper_node"), ("loop_detector", "loop_detector_node"),
         ("replay", " replay "))


def render(duration_s: float, cache: Path) -> Path:
    bag = cache / f"procedural_{duration_s:g}s_bag"
    if (bag / "metadata.yaml").exists():
        return bag
    cache.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "vigs_cli.main", "sim", "--procedural", "--procedural-duration",
                    str(duration_s), "--width", "376", "--no-depth", "--bag", str(bag), "--no-progress"],
                   cwd=ROOT, check=True)
    return bag


def role(name: str, cmdline: str, top: str) -> str:
    return NAMES.get(name) or next((r for r, key in ROLES if key in cmdline), top)


def sample(proc: subprocess.Popen, top: str, period_s: float, progress: dict) -> dict[str, list]:
    """``{role: [(wall s, RSS MB, keyframes or None)]}`` of ``proc`` and its descendants until it exits."""
    import psutil

    parent = psutil.Process(proc.pid)
    out: dict[str, list] = {}
    t0 = time.monotonic()
    while proc.poll() is None:
        now = time.monotonic() - t0
        by_role: dict[str, float] = {}
        for p in [parent, *parent.children(recursive=True)]:
            try:
                name = top if p.pid == parent.pid else role(p.name(), " ".join(p.cmdline()), "other")
                by_role[name] = by_role.get(name, 0.0) + p.memory_info().rss / 2**20
            except psutil.Error:
                pass
        for name, mb in by_role.items():
            out.setdefault(name, []).append((now, mb, progress.get("keyframes")))
        time.sleep(period_s)
    return out


def summarise(series: dict[str, list], warmup_s: float) -> dict[str, dict]:
    rows = {}
    for name, points in series.items():
        points = points[:-2] if len(points) > 8 else points   # the last samples catch the process exiting
        a = np.array([(t, mb) for t, mb, _ in points])
        kf = np.array([k if k is not None else np.nan for _, _, k in points], dtype=float)
        late = a[:, 0] >= warmup_s
        if np.isfinite(kf).any():   # while tracking: before the first sample at the final keyframe count
            late &= np.arange(len(kf)) < int(np.nanargmax(kf))
        row = {"peak_mb": round(float(a[:, 1].max()), 1), "end_mb": round(float(a[-1, 1]), 1),
               "samples": len(a)}
        if late.sum() >= 3:
            row["warm_mb"] = round(float(a[late][0, 1]), 1)
            row["slope_mb_per_min"] = round(float(np.polyfit(a[late, 0] / 60.0, a[late, 1], 1)[0]), 2)
            kf = kf[late]
            if np.isfinite(kf).sum() >= 3 and np.ptp(kf[np.isfinite(kf)]) > 0:
                ok = np.isfinite(kf)
                row["slope_mb_per_keyframe"] = round(float(np.polyfit(kf[ok], a[late][ok, 1], 1)[0]), 3)
        rows[name] = row
    return rows


def run_vigs_run(bag: Path, out: Path, period_s: float, params: str | None = None) -> dict[str, list]:
    out.mkdir(parents=True, exist_ok=True)
    extra = ["--params", params] if params else []
    proc = subprocess.Popen([sys.executable, "-m", "vigs_cli.main", "run", str(bag), "--out", str(out), *extra],
                            cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    progress: dict = {}

    def read() -> None:   # the progress bar's "kf=N" postfix
        buf = ""
        while chunk := proc.stderr.read(256):
            buf = (buf + chunk)[-4000:]
            found = re.findall(r"kf=(\d+)\D", buf)   # a number cut by the chunk is not complete
            if found:
                progress["keyframes"] = int(found[-1])
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    series = sample(proc, "vigs run", period_s, progress)
    reader.join(5)
    return series


def run_graph(bag: Path, out: Path, period_s: float, realtime: bool = False) -> dict[str, list]:
    sys.path.insert(0, str(ROOT / "tests"))
    from ros_helpers import isolated_env

    out.mkdir(parents=True, exist_ok=True)
    params = out / "params.yaml"
    params.write_text(f"frontend:\n  ros__parameters:\n    output_dir: {out}\n"
                      f"mapper:\n  ros__parameters:\n    map_path: {out / 'map.ply'}\n")
    rate = [] if realtime else ["--fast"]
    proc = subprocess.Popen([sys.executable, "-m", "vigs_cli.main", "launch", "--bag", str(bag), *rate,
                             "--params", str(params), "--settle", "5"], cwd=ROOT, env=isolated_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return sample(proc, "launcher", period_s, {})


def sizes(out: Path) -> dict[str, float]:
    return {p.name: round(p.stat().st_size / 2**20, 2) for p in sorted(out.iterdir()) if p.is_file()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vigs bench soak", description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=1800.0, help="procedural sequence length (s)")
    p.add_argument("--warmup-s", type=float, default=300.0, help="wall seconds left out of the slope")
    p.add_argument("--sample-s", type=float, default=10.0, help="RSS sampling period (s)")
    p.add_argument("--cache", default=str(ROOT / "out" / "soak"), help="the rendered bag and the run outputs")
    p.add_argument("--no-graph", action="store_true", help="only vigs run")
    p.add_argument("--no-run", action="store_true", help="only the graph")
    p.add_argument("--realtime", action="store_true", help="the graph's replay at the recorded rate (not --fast)")
    p.add_argument("--params", help="vigs run's --params (the graph runs the shipped parameters)")
    p.add_argument("--bag", help="run this bag instead of the procedural sequence (e.g. a hybrid EuRoC bag: a "
                                 "scene that is mostly new, for the growth per keyframe and per Gaussian)")
    p.add_argument("--json", help="write the results here")
    p.add_argument("--keep", action="store_true", help="keep the run folders in the cache")
    args = p.parse_args(argv)
    cache = Path(args.cache)
    bag = Path(args.bag) if args.bag else render(args.duration, cache)
    results = {}
    runs = [] if args.no_run else [("vigs run", lambda b, o, s: run_vigs_run(b, o, s, args.params))]
    runs += [] if args.no_graph else [("graph", lambda b, o, s: run_graph(b, o, s, args.realtime))]
    for name, runner in runs:
        out = Path(tempfile.mkdtemp(prefix=name.replace(" ", "_") + "_", dir=cache))
        t0 = time.monotonic()
        series = runner(bag, out, args.sample_s)
        results[name] = {"wall_s": round(time.monotonic() - t0, 1), "processes": summarise(series, args.warmup_s),
                         "outputs_mb": sizes(out), "series": series}
        if not args.keep:
            shutil.rmtree(out)
        print(f"\n{name}: {results[name]['wall_s']} s wall, outputs {results[name]['outputs_mb']}")
        print(f"{'process':>20} {'peak MB':>8} {'warm MB':>8} {'end MB':>8} {'MB/min':>7} {'MB/kf':>6}")
        for proc_name, row in results[name]["processes"].items():
            print(f"{proc_name:>20} {row['peak_mb']:>8} {row.get('warm_mb', '-'):>8} {row['end_mb']:>8} "
                  f"{row.get('slope_mb_per_min', '-'):>7} {row.get('slope_mb_per_keyframe', '-'):>6}")
    print(f"\nload {os.getloadavg()[0]:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
