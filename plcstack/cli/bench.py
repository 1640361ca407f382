"""``plcstack bench``: the benchmark suite (codecs, one connection vs the floor, fan-out, peers).

The suite's code is the top-level ``benchmarks`` package of the source tree, beside ``plcstack/``;
it is deliberately not installed with the wheel (it is a development tool with its own cases and
fixtures). This command finds it in this order: the directory that contains the ``plcstack``
package being run (a source checkout, also after ``pip install -e .``), else an importable
``benchmarks`` package. From an installed wheel without the source tree it says so and exits 2.

The measurements run in a worker thread with their own event loop per loop kind (asyncio, and
uvloop when installed), so both loops are measured the same way; fan-out cases run in child
processes (see ``benchmarks/cases/fanout.py``).
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

from plcstack.errors import AddressError


def register(subparsers: Any) -> None:
    bench = subparsers.add_parser(
        "bench",
        help="benchmark codecs, one connection against the raw-asyncio floor, fan-out, peers",
        description="Measure plcstack against a raw asyncio floor on in-process simulators. "
        "Needs the source tree (the benchmarks/ package beside plcstack/).",
    )
    size = bench.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="short run, < 60 s on 2 cores")
    size.add_argument("--smoke", action="store_true", help=argparse.SUPPRESS)
    bench.add_argument("--json", metavar="FILE", help='write {"results": [...]} to FILE')
    bench.add_argument("--plot", metavar="FILE.png", help="write a PNG chart of ops/s against N")
    bench.add_argument(
        "--loop",
        choices=("all", "asyncio", "uvloop"),
        default="all",
        help="event loop(s) to measure (default: asyncio, and uvloop when installed)",
    )
    bench.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    bench.set_defaults(func=run_bench)


def load_benchmarks() -> ModuleType:
    """Import ``benchmarks.suite``: the source tree's own first, else an importable one."""
    root = Path(__file__).resolve().parents[2]
    if (root / "benchmarks" / "suite.py").is_file():
        if str(root) not in sys.path:
            sys.path.insert(0, str(root))
        return importlib.import_module("benchmarks.suite")
    try:
        return importlib.import_module("benchmarks.suite")
    except ModuleNotFoundError as exc:
        if exc.name not in ("benchmarks", "benchmarks.suite"):
            raise
    raise AddressError(
        "plcstack bench needs the source tree: the benchmarks/ package was not found next to "
        f"{root / 'plcstack'} (run it from a git checkout, e.g. after pip install -e .)"
    )


async def run_bench(args: argparse.Namespace) -> int:
    suite = load_benchmarks()
    report = importlib.import_module("benchmarks.report")
    plan = suite.PLANS["smoke" if args.smoke else "quick" if args.quick else "full"]
    loops = suite.available_loops()
    if args.loop != "all":
        loops = [entry for entry in loops if entry[0] == args.loop]
        if not loops:
            raise AddressError(f"event loop {args.loop!r} is not installed")
    log = None if args.quiet else sys.stderr
    # A thread of its own: the suite creates one event loop per loop kind (asyncio.Runner).
    results = await asyncio.to_thread(suite.run_suite, plan, loops=loops, log=log)
    print(report.format_table(results))
    if args.json:
        report.write_json(args.json, results, {"plan": plan.name, "loops": [n for n, _ in loops]})
    if args.plot:
        report.write_plot(args.plot, results, f"PLCSTACK BENCH ({plan.name}): OPS/S AGAINST N")
    return 0
