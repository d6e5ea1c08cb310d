"""``vigs eval GT EST``: accuracy of an estimated trajectory against ground truth.

GT and EST are each a TUM text file or a EuRoC CSV (recognised by content). Prints a table, or with
``--json`` the dict of :func:`vigs_core.eval.evaluate_trajectory`. Exit status 0, or 2 when a file
cannot be read or the trajectories cannot be evaluated (the reason goes to stderr).
"""
from __future__ import annotations

import argparse
import json
import sys

from vigs_core.eval.alignment import ALIGN_MODES
from vigs_core.eval.metrics import RPE_UNITS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("gt", help="ground-truth trajectory: TUM text or EuRoC CSV")
    parser.add_argument("est", help="estimated trajectory: TUM text or EuRoC CSV")
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


def run(args: argparse.Namespace) -> int:
    from vigs_core.eval import evaluate_trajectory, recall_key
    from vigs_core.io import read_trajectory

    try:
        gt = read_trajectory(args.gt)
        est = read_trajectory(args.est)
        result = evaluate_trajectory(
            gt,
            est,
            align=args.align,
            thresholds=tuple(args.recall),
            max_diff_s=args.max_diff,
            rpe_delta=args.rpe_delta,
            rpe_unit=args.rpe_unit,
        )
    except (OSError, ValueError) as error:
        print(f"vigs eval: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_table(result, [recall_key(t) for t in args.recall]))
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
