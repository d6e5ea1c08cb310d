"""Tracking speed and accuracy, side by side with another commit (issue 22 benchmark).

Each run is ``vigs run BAG`` (visual-inertial odometry with loop closure, mapping off) in a child process on
the whole hybrid bag of a shared sequence (``out/sim/<SEQ>_bag``, rendered by ``vigs sim --euroc ... --width 376
--no-depth --bag``). Rows, per sequence and code version (this checkout, ``--base REV`` in a git worktree of
that commit, and every ``--variant NAME=FILE`` of this checkout with extra parameters):

* ``fps``: frames per second of wall time (report.json ``frames_per_s``);
* ``cpu_ms``: user + system CPU per frame of the run and its children (loop closure included), from
  ``getrusage(RUSAGE_CHILDREN)``: the figure the 25 ms target is about;
* ``flow`` / ``ba`` / ``track`` / ``vio`` ms: the run's per-stage wall time per frame (report.json ``timings_s``:
  DIS flows, BA, pose-only tracking, the inertial initialisation);
* ``ate_se3`` / ``ate_sim3`` cm and ``rec10`` (recall@10cm, SE(3)) of the body trajectory;
* ``rrd_mb``: the size of the rerun recording of the ``--rrd`` version (``head+rrd``: this checkout with
  ``vigs run --rrd``), 0 for the others.

Runs of one sequence alternate between the versions (``--repeat`` rounds), so old and new share the machine's
load; the 1-minute load average is printed before and after. Time it on a quiet machine.

    vigs bench tracking [--sequences V1_01_easy V2_01_easy MH_03_medium] [--base REV] [--variant NAME=FILE]
                        [--rrd] [--repeat 1] [--bags out/sim] [--keep DIR] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
SEQUENCES = ("V1_01_easy", "V2_01_easy", "MH_03_medium")
STAGES = {"flow": "flow", "ba": "ba", "track": "tracking", "vio": "vio_init"}
RUN = "import sys; from vigs_cli.main import main; sys.argv[0] = 'vigs'; sys.exit(main())"


def params_file(folder: Path, name: str, extra: Path | None, mapping: dict) -> Path:
    """A ``--params`` file for ``vigs run``: ``extra``'s frontend parameters (ROS layout) with the ``mapping``
    settings set over them (``{"enabled": False}`` for this benchmark)."""
    doc = (yaml.safe_load(extra.read_text()) if extra else None) or {}
    front = doc.setdefault("frontend", {}).setdefault("ros__parameters", {})
    front.setdefault("mapping", {}).update(mapping)
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def run_once(code: Path, bag: Path, params: Path, out: Path, rrd: bool = False) -> dict:
    """One ``vigs run`` of ``code`` (a checkout), recording to ``out/run.rrd`` with ``rrd``; the report with the
    CPU time of the run and its children."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    env = {**os.environ, "PYTHONPATH": str(code)}
    extra = ["--rrd", str(out / "run.rrd")] if rrd else []
    proc = subprocess.run([sys.executable, "-c", RUN, "run", str(bag), "--params", str(params), "--out", str(out),
                           *extra], cwd=code, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"vigs run in {code} on {bag} exited {proc.returncode}: {proc.stderr[-2000:]}")
    report = json.loads((out / "report.json").read_text())
    report["cpu_s"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    report["rrd_mb"] = round((out / "run.rrd").stat().st_size / 1e6, 1) if rrd else 0.0
    return report


def row(sequence: str, label: str, report: dict) -> dict:
    n = report["frames"]
    timings = report.get("timings_s", {})
    se3, sim3 = report.get("accuracy_se3") or {}, report.get("accuracy") or {}
    out = {"sequence": sequence, "version": label, "frames": n, "fps": report["frames_per_s"],
           "cpu_ms": round(1000 * report["cpu_s"] / n, 1)}
    out.update({f"{k}_ms": round(1000 * timings.get(v, 0.0) / n, 1) for k, v in STAGES.items()})
    out.update({"ate_se3": round(100 * se3.get("ate_rmse", float("nan")), 2),
                "ate_sim3": round(100 * sim3.get("ate_rmse", float("nan")), 2),
                "rec10": round(se3.get("recall@0.1", float("nan")), 3), "rrd_mb": report["rrd_mb"]})
    return out


def print_table(rows: list[dict]) -> None:
    cols = list(rows[0])
    width = {c: max(len(c), *(len(str(r[c])) for r in rows)) for c in cols}
    print("  ".join(c.rjust(width[c]) for c in cols))
    for r in rows:
        print("  ".join(str(r[c]).rjust(width[c]) for c in cols), flush=True)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments every side-by-side ``vigs run`` benchmark takes (this one and ``vigs bench mapping``)."""
    p.add_argument("--sequences", nargs="+", default=list(SEQUENCES))
    p.add_argument("--bags", default=str(ROOT / "out" / "sim"), help="folder of the <SEQ>_bag hybrid bags")
    p.add_argument("--base", help="git commit or tag to compare with (checked out in a temporary worktree)")
    p.add_argument("--variant", action="append", default=[], metavar="NAME=FILE",
                   help="this checkout with these extra parameters (vigs run --params layout)")
    p.add_argument("--repeat", type=int, default=1, help="rounds over the versions per sequence")
    p.add_argument("--keep", help="keep the run folders here")
    p.add_argument("--json", help="write the rows here")


def compare(p: argparse.ArgumentParser, args: argparse.Namespace, mapping: dict, make_row, rrd: bool = False) -> int:
    """Run every version on every sequence (alternating per sequence), print the rows of ``make_row(sequence,
    label, report)`` as a table; ``mapping`` goes into every version's parameters (:func:`params_file`)."""
    variants = [v.split("=", 1) for v in args.variant]
    if any(len(v) != 2 or not Path(v[1]).is_file() for v in variants):
        p.error("--variant takes NAME=FILE with an existing parameter file")
    bags = {s: Path(args.bags) / f"{s}_bag" for s in args.sequences}
    missing = [str(b) for b in bags.values() if not b.exists()]
    if missing:
        p.error(f"no hybrid bag {missing}; render with: vigs sim --euroc ../shared/data/euroc/SEQ --width 376 "
                "--no-depth --bag out/sim/SEQ_bag")
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="vigs_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    versions = [("head", ROOT, params_file(work, "head", None, mapping), False)]
    versions += [(name, ROOT, params_file(work, name, Path(file), mapping), False) for name, file in variants]
    if rrd:
        versions.append(("head+rrd", ROOT, versions[0][2], True))
    worktree = None
    try:
        if args.base:
            worktree = work / "base_checkout"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(worktree), args.base],
                           check=True, capture_output=True)
            versions.insert(0, (f"base {args.base}", worktree, params_file(work, "base", None, mapping), False))
        print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
        rows = []
        for seq, bag in bags.items():
            for rnd in range(args.repeat):
                for label, code, params, with_rrd in versions:
                    out = work / f"{seq}_{label.split()[0]}_{rnd}"
                    shutil.rmtree(out, ignore_errors=True)
                    out.mkdir(parents=True)
                    rows.append(make_row(seq, label, run_once(code, bag, params, out, with_rrd)))
                    print(json.dumps(rows[-1]), flush=True)
        print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        print_table(rows)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
    finally:
        if worktree is not None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(worktree)],
                           capture_output=True)
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vigs bench tracking", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.add_argument("--rrd", action="store_true",
                   help="also this checkout recording to a rerun file (vigs run --rrd): what logging costs")
    args = p.parse_args(argv)
    return compare(p, args, {"enabled": False}, row, rrd=args.rrd)


if __name__ == "__main__":
    raise SystemExit(main())
