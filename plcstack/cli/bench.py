"""``plcstack bench``: the benchmark suite (codecs, one connection, fan-out, fleet, peers).

The suite is the ``plcstack.bench`` package, installed with the wheel, so the command works from
any install. Standalone developer scripts that need extra services (brokers, databases) stay in
the repository's ``benchmarks/`` directory and are not part of this command.

The measurements run in a worker thread with their own event loop per loop kind (asyncio, and
uvloop when installed), so both loops are measured the same way; fan-out and fleet cases run in
child processes (see ``plcstack/bench/cases/fanout.py`` and ``fleet.py``).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import threading
from collections.abc import Callable
from typing import Any, TypeVar

from plcstack.errors import AddressError

T = TypeVar("T")


def register(subparsers: Any) -> None:
    bench = subparsers.add_parser(
        "bench",
        help="benchmark codecs, one connection against the raw-asyncio floor, fan-out, peers",
        description="Measure plcstack against a raw asyncio floor on in-process simulators. "
        "Runs from any install (the suite is the plcstack.bench package).",
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
    bench.add_argument(
        "--only",
        action="append",
        choices=("codec", "conn", "fanout", "fleet", "peer"),
        help="run only this group of cases (repeatable; default: all)",
    )
    bench.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    bench.set_defaults(func=run_bench)


async def _in_daemon_thread(work: Callable[[], T]) -> T:
    """Run ``work`` in a daemon thread and await its result.

    A thread of its own because the suite creates one event loop per loop kind
    (``asyncio.Runner``), which cannot nest in this one; a daemon thread (not the default
    executor, whose threads are joined at exit) so that Ctrl-C ends a long run at once.
    """
    loop = asyncio.get_running_loop()
    done: asyncio.Future[T] = loop.create_future()

    def deliver(result: T | None, error: BaseException | None) -> None:
        if done.cancelled():
            return
        if error is not None:
            done.set_exception(error)
        else:
            done.set_result(result)  # type: ignore[arg-type]

    def target() -> None:
        try:
            result = work()
        except BaseException as exc:  # handed to the awaiting coroutine
            loop.call_soon_threadsafe(deliver, None, exc)
        else:
            loop.call_soon_threadsafe(deliver, result, None)

    threading.Thread(target=target, name="plcstack-bench", daemon=True).start()
    # Wake up now and then: the kernel may deliver SIGINT to the worker thread, and Python runs
    # its handler only when the main thread executes bytecode (it would sleep in epoll forever).
    while not done.done():
        await asyncio.wait({done}, timeout=0.2)
    return done.result()


async def run_bench(args: argparse.Namespace) -> int:
    from plcstack.bench import report, suite  # imported on use: ``plcstack --help`` stays fast

    plan = suite.PLANS["smoke" if args.smoke else "quick" if args.quick else "full"]
    loops = suite.available_loops()
    if args.loop != "all":
        loops = [entry for entry in loops if entry[0] == args.loop]
        if not loops:
            raise AddressError(f"event loop {args.loop!r} is not installed")
    log = None if args.quiet else sys.stderr
    results = await _in_daemon_thread(
        lambda: suite.run_suite(
            plan, loops=loops, log=log, only=frozenset(args.only) if args.only else None
        )
    )
    print(report.format_table(results))
    if args.json:
        report.write_json(args.json, results, {"plan": plan.name, "loops": [n for n, _ in loops]})
    if args.plot:
        report.write_plot(args.plot, results, f"PLCSTACK BENCH ({plan.name}): OPS/S AGAINST N")
    return 0
