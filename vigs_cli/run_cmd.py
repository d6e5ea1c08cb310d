"""``vigs run INPUT [--params FILE] [--out DIR]``: the dense monocular odometry over an EuRoC ASL folder or a
ROS 2 / ROS 1 bag; writes trajectories (TUM) and report.json (timings, frames/s, memory, accuracy)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = "run the in-process pipeline on an EuRoC ASL folder or a ROS bag; write trajectories and a report"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="EuRoC ASL folder (with mav0/) or ROS 2 bag directory / ROS 1 .bag")
    parser.add_argument("--params", help="YAML with a 'frontend: ros__parameters:' section (e.g. params/frontend.yaml)")
    parser.add_argument("--out", default="vigs_out", help="output folder (default: vigs_out)")
    parser.add_argument("--max-frames", type=int, help="stop after this many frames")
    parser.add_argument("--stride", type=int, help="use every n-th frame")
    parser.add_argument("--image-topic", help="bag image topic (default: found by message type)")
    parser.add_argument("--refine", type=int, metavar="N",
                        help="colour-refinement iterations of the map after the run (default: the parameters' "
                             "mapping.final_refine_iterations, 100); each takes about 20-30 ms of CPU, and an "
                             "offline map gains from thousands (docs/benchmarks.md, issue 23)")
    parser.add_argument("--frames-from", metavar="FILE",
                        help="process only the frames whose stamps (ns, first column) FILE lists, each at the yield "
                             "point of the second column if any, and skip the rest: the frontend node's "
                             "frames_processed.txt replays a live run with its skips and interleaving")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    viz = parser.add_mutually_exclusive_group()
    viz.add_argument("--viz", nargs="?", const="spawn", metavar="URL",
                     help="show the run live in rerun: start a local viewer, or stream to the running viewer at URL "
                          "(e.g. rerun+http://laptop:9876/proxy)")
    viz.add_argument("--rrd", metavar="FILE", help="record the run to a rerun file (open it with `rerun FILE`)")


def run(args: argparse.Namespace) -> int:
    from vigs_core.gc_freeze import freeze_startup_objects
    from vigs_core.heap import single_arena

    single_arena()   # before the run starts its threads (frame reader, senders to the workers)
    from vigs_core.mapping.process import MappingProcessError
    from vigs_core.system import apply_overrides, load_config, run_pipeline

    try:
        cfg = load_config(args.params)
    except (KeyError, OSError, ValueError) as err:
        print(f"vigs run: bad --params: {err}", file=sys.stderr)
        return 2
    options = {"max_frames": ("--max-frames", args.max_frames), "frame_stride": ("--stride", args.stride),
               "image_topic": ("--image-topic", args.image_topic),
               "mapping": ("--refine", None if args.refine is None else {"final_refine_iterations": args.refine})}
    for key, (option, value) in options.items():
        if value is None:
            continue
        try:   # checked like a parameter file's value (type and range)
            apply_overrides(cfg, {key: value})
        except ValueError as err:
            print(f"vigs run: bad {option}: {err}", file=sys.stderr)
            return 2
    schedule = None
    if args.frames_from is not None:
        from vigs_core.io import read_frame_schedule

        try:
            schedule = read_frame_schedule(args.frames_from)
        except (OSError, ValueError) as err:
            print(f"vigs run: bad --frames-from: {err}", file=sys.stderr)
            return 2
    again = freeze_startup_objects()   # the imported modules, then the warmed-up run: full collections skip them
    try:
        report = run_pipeline(args.input, cfg, args.out, progress=not args.no_progress, schedule=schedule,
                              viz=args.viz or args.rrd)
    except (FileNotFoundError, ValueError) as err:
        print(f"vigs run: {err}", file=sys.stderr)
        return 2
    except MappingProcessError as err:   # printed in full above; the other outputs were written
        print(f"vigs run: {str(err).splitlines()[0]} (the other outputs are in {args.out})", file=sys.stderr)
        return 1
    finally:
        again.cancel()   # only while the run goes on (a caller in the same process keeps its collector)
    summary = {k: report[k] for k in ("frames", "frames_posed", "keyframes", "frames_per_s", "peak_rss_mb")}
    acc = report.get("accuracy", {})
    summary.update({k: acc[k] for k in ("ate_rmse", "recall@0.1", "scale") if k in acc})
    print(json.dumps(summary))
    names = ("trajectory.txt", "trajectory_cam.txt", "odometry.txt", "keyframes.txt", "frame_status.txt", "report.json",
             "report.html", "map.ply")
    written = [n for n in names if (Path(args.out) / n).is_file()]   # report.html fails apart (a warning above)
    print(f"wrote {args.out}/{', '.join(written)}")
    # interrupted: the outputs are written, the exit code is the shell's for the signal (128 + its number)
    return {"SIGINT": 130, "SIGTERM": 143}.get(report.get("interrupted"), 0)
