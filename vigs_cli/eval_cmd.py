"""``vigs eval GT EST [EST ...] [--html OUT.html]``: accuracy of estimated trajectories against ground truth.

GT and EST are each a TUM text file or a EuRoC CSV (recognised by content). Prints a table, or with
``--json`` the dict of :func:`vigs_core.eval.evaluate_trajectory`; several estimates give one table each (headed
by the file) or a JSON object keyed by file. ``--html`` also writes a plotted report with every estimate overlaid
and a table of their metrics (:mod:`vigs_core.eval.report_html`; an estimate in a ``vigs run`` output folder
brings its keyframes, loops, scale, biases and timings). Exit status 0, or 2 when a file cannot be read or the
trajectories cannot be evaluated (the reason goes to stderr).
"""
from __future__ import annotations

import argparse
import json
import sys

from vigs_core.eval.alignment import ALIGN_MODES
from vigs_core.eval.metrics import RPE_UNITS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("gt", help="ground-truth trajectory: TUM text or EuRoC CSV")
    parser.add_argument("est", nargs="+", help="estimated trajectory: TUM text or EuRoC CSV; several are compared")
    parser.add_argument(
        "--align",
        choices=ALIGN_MODES,
        default="sim3",
        help="alignment of the estimate to the ground truth: sim3 (monocular), se3, posyaw (4-DoF, "
        "visual-inertial), none (default: sim3)",
    )
    parser.add_argument(
        "--recall",
        type=float,
        nargs="+",
        default=[0.05, 0.10],
        metavar="M",
        help="recall thresholds in metres (default: 0.05 0.10)",
    )
    parser.add_argument(
        "--rpe-delta", type=float, default=None, metavar="D", help="also compute RPE over pose pairs D apart"
    )
    parser.add_argument(
        "--rpe-unit", choices=RPE_UNITS, default="m", help="unit of --rpe-delta: m (path length) or s (time)"
    )
    parser.add_argument(
        "--max-diff", type=float, default=0.02, metavar="S", help="largest stamp difference to pair, s (default 0.02)"
    )
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--html", metavar="OUT.html",
                        help="also write a plotted report of the estimates against the ground truth (figures in "
                             "OUT_figures/ beside it)")


def run(args: argparse.Namespace) -> int:
    from vigs_core.eval import evaluate_trajectory, recall_key
    from vigs_core.io import read_trajectory

    try:
        gt = read_trajectory(args.gt)
        results = [
            evaluate_trajectory(
                gt,
                read_trajectory(path),
                align=args.align,
                thresholds=tuple(args.recall),
                max_diff_s=args.max_diff,
                rpe_delta=args.rpe_delta,
                rpe_unit=args.rpe_unit,
            )
            for path in args.est
        ]
    except (OSError, ValueError) as error:
        print(f"vigs eval: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(results[0] if len(results) == 1 else dict(zip(args.est, results)), indent=2))
    else:
        tables = [format_table(result, [recall_key(t) for t in args.recall]) for result in results]
        print(tables[0] if len(tables) == 1 else "\n\n".join(f"== {p}\n{t}" for p, t in zip(args.est, tables)))
    return write_html(args, gt) if args.html else 0


def write_html(args: argparse.Namespace, gt) -> int:
    """The ``--html`` report of the estimates (the path goes to stderr, stdout keeps the tables or JSON)."""
    from vigs_core.eval.report_html import ReportConfig, load_run, write_report

    config = ReportConfig(align=args.align, max_diff_s=args.max_diff, recall=tuple(args.recall))
    try:
        page = write_report([load_run(path) for path in args.est], args.html, gt, config,
                            title=f"vigs eval against {args.gt}")
    except (OSError, ValueError) as error:
        print(f"vigs eval: --html: {error}", file=sys.stderr)
        return 2
    print(f"vigs eval: wrote {page} (figures in {page.stem}_figures/)", file=sys.stderr)
    return 0


def format_table(result: dict, recall_keys: list[str]) -> str:
    """Plain-text table of an :func:`evaluate_trajectory` result."""
    rows = [
        ("alignment", result["align"]),
        ("poses (gt / est / matched)", f"{result['n_gt']} / {result['n_est']} / {result['n_matched']}"),
        ("scale", f"{result['scale']:.6f}"),
        ("ATE RMSE [m]", f"{result['ate_rmse']:.6f}"),
        ("ATE mean [m]", f"{result['ate_mean']:.6f}"),
        ("ATE median [m]", f"{result['ate_median']:.6f}"),
        ("ATE max [m]", f"{result['ate_max']:.6f}"),
    ]
    rows += [(key, f"{result[key]:.4f}") for key in recall_keys]
    if "rpe_pairs" in result:
        over = f"{result['rpe_delta']:g} {result['rpe_unit']}"
        rows += [
            (f"RPE pairs ({over})", str(result["rpe_pairs"])),
            ("RPE trans RMSE [m]", f"{result['rpe_trans_rmse']:.6f}"),
            ("RPE trans mean [m]", f"{result['rpe_trans_mean']:.6f}"),
            ("RPE rot RMSE [deg]", f"{result['rpe_rot_rmse']:.6f}"),
            ("RPE rot mean [deg]", f"{result['rpe_rot_mean']:.6f}"),
        ]
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)
