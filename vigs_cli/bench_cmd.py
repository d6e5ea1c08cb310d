"""``vigs bench NAME [ARGS...]``: run a benchmark script ``benchmarks/NAME.py`` that prints a table.

Benchmarks live outside the package (they may read ../shared data); each defines ``main(argv)``.
"""
from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent.parent / "benchmarks"


def available() -> list[str]:
    return sorted(p.stem for p in BENCH_DIR.glob("*.py") if not p.name.startswith("_"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", help="benchmark name: one of " + ", ".join(available()))
    parser.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the benchmark")


def run(args: argparse.Namespace) -> int:
    if args.name not in available():
        print(f"vigs bench: no benchmark '{args.name}'; available: {', '.join(available())}", file=sys.stderr)
        return 2
    module = runpy.run_path(str(BENCH_DIR / f"{args.name}.py"), run_name="vigs_bench")
    return int(module["main"](args.args) or 0)
