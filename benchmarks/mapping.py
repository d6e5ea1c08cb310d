"""The Gaussian map on whole sequences with estimated poses, side by side with another commit (issue 23 benchmark).

Each run is ``vigs run BAG`` with mapping on (visual-inertial odometry, loop closure, the mapper in its worker
process, then ``--refine`` colour-refinement iterations) on the whole hybrid bag of a shared sequence
(``out/sim/<SEQ>_bag``), for this checkout, ``--base REV`` and every ``--variant NAME=FILE``, alternating per
sequence as ``vigs bench tracking`` does (whose runner this uses). Rows:

* ``fps``: tracking frames per second (report.json ``frames_per_s``, the end's wait for the mapper excluded);
* ``cpu_ms``: user + system CPU per frame of the run and its children (tracking, mapping, loop closure, the
  evaluation renders and the refinement included);
* ``kf``, ``kf_per_s``: keyframes mapped and the mapper's keyframes per second of its own wall time;
  ``kept``: those still held at the end (the rest released by keyframe culling);
  ``wait_s``: how long the run waited for the mapper's backlog at the end;
* ``gaussians``, ``render``: the map's size and the render size;
* ``psnr`` / ``ssim``: non-keyframe frames rendered at their final poses, online (before the refinement) and
  ``psnr_ref`` / ``ssim_ref`` after it;
* ``ate_se3`` cm: the body trajectory's SE(3) ATE (mapping must not cost tracking accuracy).

    vigs bench mapping [--sequences V1_01_easy V2_01_easy MH_03_medium] [--base REV] [--variant NAME=FILE]
                       [--refine 100] [--repeat 1] [--bags out/sim] [--keep DIR] [--json OUT]
"""
from __future__ import annotations

import argparse
import math
import runpy
from pathlib import Path

TRACKING = runpy.run_path(str(Path(__file__).with_name("tracking.py")))


def row(sequence: str, label: str, report: dict) -> dict:
    n = report["frames"]
    mapping = report.get("mapping") or {}
    online, refined = mapping.get("online") or {}, mapping.get("refined") or {}
    se3 = report.get("accuracy_se3") or {}
    render = mapping.get("render_size") or []
    return {"sequence": sequence, "version": label, "frames": n, "fps": report["frames_per_s"],
            "cpu_ms": round(1000 * report["cpu_s"] / n, 1), "kf": mapping.get("keyframes_mapped"),
            "kept": (mapping["keyframes_mapped"] - mapping["keyframes_released"]
                     if "keyframes_released" in mapping else None),
            "kf_per_s": mapping.get("keyframes_per_s"), "wait_s": mapping.get("wait_at_end_s"),
            "gaussians": mapping.get("gaussians"), "render": "x".join(str(v) for v in render),
            "psnr": online.get("psnr", math.nan), "ssim": online.get("ssim", math.nan),
            "psnr_ref": refined.get("psnr", math.nan), "ssim_ref": refined.get("ssim", math.nan),
            "ate_se3": round(100 * se3.get("ate_rmse", math.nan), 2)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vigs bench mapping", description=__doc__.split("\n\n")[0])
    TRACKING["add_arguments"](p)
    p.add_argument("--refine", type=int, default=100, help="final colour-refinement iterations of every run")
    args = p.parse_args(argv)
    return TRACKING["compare"](p, args, {"enabled": True, "final_refine_iterations": args.refine}, row)


if __name__ == "__main__":
    raise SystemExit(main())
