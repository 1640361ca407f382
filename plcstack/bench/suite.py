"""Which cases run, how long, on which event loops: the whole of ``plcstack bench``.

Plans:

* ``quick`` -- every case with short repeats; must finish in < 60 s on a 2-core machine
  (about 20 s per event loop here, 40-50 s with uvloop and the peer). Fan-out N = 10, 100,
  1000 for E71 TCP through the poller.
* ``full``  -- longer repeats, fan-out also for FETCH/WRITE and S5-LAN, both stack kinds
  (poller and plain clients); about 5 minutes per event loop. The 10 Hz fleet (N = 100,
  1000; in ``quick`` N = 100 only) against responders in another process on their own CPU.
* ``smoke`` -- tiny sizes for the test suite: exercises every code path, measures nothing useful.

Failures never abort the run: a case that cannot run (protocol not merged, peer not installed) or
that fails becomes a row with a note, so one broken protocol does not hide the others' numbers.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import os
import statistics
import sys
import time
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass
from typing import Any, TextIO, TypeVar

from plcstack.bench.cases import WORDS, Unavailable, fleet
from plcstack.bench.cases.conn import run_conn_case
from plcstack.bench.cases.fanout import series_from_summary, spawn
from plcstack.bench.cases.peers import PEER_PROTOCOLS, hsl_available
from plcstack.bench.cases.protocols import PROTOCOLS, by_key
from plcstack.bench.runner import Result, measure_sync

__all__ = ["GROUPS", "PLANS", "Plan", "available_loops", "run_suite"]

#: the case groups, in report order (``plcstack bench --only``)
GROUPS = frozenset({"codec", "conn", "fanout", "fleet", "peer"})

LoopFactory = Callable[[], asyncio.AbstractEventLoop]
T = TypeVar("T")


@dataclass(frozen=True)
class Plan:
    name: str
    repeats: int
    conn_duration: float
    warmup: float
    codec_time: float
    conn_kinds: tuple[str, ...]
    fanout_protocols: tuple[str, ...]
    fanout_ns: tuple[int, ...]
    #: stack kinds measured against the floor; "poll" falls back to "clients" when unavailable
    fanout_kinds: tuple[str, ...]
    fanout_duration: float
    fanout_repeats: int
    peer_ns: tuple[int, ...]
    #: the 10 Hz fleet against responders in another process (cases/fleet.py)
    fleet_ns: tuple[int, ...] = ()
    fleet_duration: float = 1.0
    fleet_warmup: float = 1.0
    #: floor and stack children alternate this many times; the ratio is the median of the pairs
    fleet_repeats: int = 1
    #: one-connection cases: floor and stack windows alternate this many times (0: ``repeats``)
    conn_repeats: int = 0


PLANS: dict[str, Plan] = {
    "smoke": Plan(
        name="smoke", repeats=1, conn_duration=0.02, warmup=0.0, codec_time=0.001,
        conn_kinds=("read", "write"), fanout_protocols=("e71+tcp",), fanout_ns=(2,),
        fanout_kinds=("poll", "clients"), fanout_duration=0.05, fanout_repeats=1, peer_ns=(2,),
        fleet_ns=(2,), fleet_duration=0.2, fleet_warmup=0.2,
    ),
    "quick": Plan(
        name="quick", repeats=3, conn_duration=0.06, warmup=0.05, codec_time=0.02, conn_repeats=5,
        conn_kinds=("read", "write"), fanout_protocols=("e71+tcp",), fanout_ns=(10, 100, 1000),
        fanout_kinds=("poll",), fanout_duration=0.25, fanout_repeats=3, peer_ns=(10,),
        fleet_ns=(100,), fleet_duration=1.0, fleet_warmup=0.5,
    ),
    "full": Plan(
        name="full", repeats=5, conn_duration=0.3, warmup=0.2, codec_time=0.2, conn_repeats=9,
        conn_kinds=("read", "write"), fanout_protocols=("e71+tcp", "fetchwrite", "s5lan"),
        fanout_ns=(10, 100, 1000), fanout_kinds=("poll", "clients"), fanout_duration=1.0,
        fanout_repeats=5, peer_ns=(10, 100, 1000),
        fleet_ns=(100, 1000), fleet_duration=3.0, fleet_warmup=1.0, fleet_repeats=3,
    ),
}  # fmt: skip


def available_loops() -> list[tuple[str, LoopFactory]]:
    """asyncio's default loop, plus uvloop when importable (optional extra ``plcstack[uvloop]``)."""
    loops: list[tuple[str, LoopFactory]] = [("asyncio", asyncio.new_event_loop)]
    try:
        uvloop = importlib.import_module("uvloop")
    except ImportError:
        return loops
    loops.append(("uvloop", uvloop.new_event_loop))
    return loops


def run_suite(
    plan: Plan,
    *,
    loops: list[tuple[str, LoopFactory]] | None = None,
    log: TextIO | None = sys.stderr,
    only: frozenset[str] | None = None,
) -> list[Result]:
    """Run every case of ``plan`` (or of the groups in ``only``); the rows in report order."""
    loops = loops if loops is not None else available_loops()
    groups = GROUPS if only is None else only
    started = time.perf_counter()

    def say(text: str) -> None:
        if log is not None:
            print(f"[{time.perf_counter() - started:5.1f}s] {text}", file=log, flush=True)

    results: list[Result] = []
    if "codec" in groups:
        results += run_codecs(plan, say)
    for loop_name, factory in loops:
        conn_repeats = plan.conn_repeats or plan.repeats
        with asyncio.Runner(loop_factory=factory) as runner, pinned_to_one_cpu():
            for case in PROTOCOLS if "conn" in groups else ():
                for kind in plan.conn_kinds:
                    name = f"conn/{case.key}/{kind}{WORDS}"
                    say(f"{name} on {loop_name}")
                    # a hung peer (or a simulator that broke on this loop) must not hang the run
                    limit = 20.0 + 2 * conn_repeats * (plan.conn_duration + plan.warmup)
                    try:
                        results.append(
                            runner.run(
                                _bounded(
                                    limit,
                                    run_conn_case(
                                        case,
                                        kind,  # type: ignore[arg-type]
                                        loop_name=loop_name,
                                        repeats=conn_repeats,
                                        duration=plan.conn_duration,
                                        warmup=plan.warmup,
                                    ),
                                )
                            )
                        )
                    except Unavailable as exc:
                        results.append(Result.skipped(name, loop_name, 1, str(exc), group="conn"))
                    except Exception as exc:  # a broken case must not hide the others
                        results.append(
                            Result.skipped(name, loop_name, 1, _failed(exc), group="conn")
                        )
        if "fanout" in groups:
            results += run_fanout(plan, loop_name, say)
        if "fleet" in groups:
            results += run_fleet(plan, loop_name, say)
    if "peer" in groups:
        results += run_peers(plan, results, say)
    return results


@contextlib.contextmanager
def pinned_to_one_cpu() -> Iterator[None]:
    """Run the one-connection cases on one CPU (the first this process may use; restored after):
    simulator, floor and stack share one thread, and a thread that migrates between cores pays
    cold caches at random moments, on either side. No-op where affinity is not supported."""
    try:
        allowed = os.sched_getaffinity(0)
    except (AttributeError, OSError):
        yield
        return
    with contextlib.suppress(OSError):
        os.sched_setaffinity(0, {min(allowed)})
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(0, allowed)


def _failed(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return f"FAILED: timed out ({exc or 'the simulator did not answer'})"
    return f"FAILED: {type(exc).__name__}: {exc}"


async def _bounded(seconds: float, coro: Coroutine[Any, Any, T]) -> T:
    try:
        async with asyncio.timeout(seconds):
            return await coro
    except TimeoutError:
        raise TimeoutError(f"case did not finish within {seconds:g} s") from None


def run_codecs(plan: Plan, say: Callable[[str], None]) -> list[Result]:
    rows: list[Result] = []
    for case in PROTOCOLS:
        if case.codec is None:
            continue
        for kind in plan.conn_kinds:
            name = f"codec/{case.key}/{kind}{WORDS}"
            say(name)
            try:
                ops = case.codec()
            except Unavailable as exc:
                rows.append(Result.skipped(name, "-", 1, str(exc), group="codec"))
                continue
            except Exception as exc:
                rows.append(Result.skipped(name, "-", 1, _failed(exc), group="codec"))
                continue
            stack_fn = ops.stack_read if kind == "read" else ops.stack_write
            floor_fn = ops.floor_read if kind == "read" else ops.floor_write
            stack = measure_sync(stack_fn, repeats=plan.repeats, min_time=plan.codec_time)
            floor = measure_sync(floor_fn, repeats=plan.repeats, min_time=plan.codec_time)
            row = Result.from_series(name, "-", 1, stack, floor, group="codec")
            row.us_per_op = 1e6 / row.ops_per_s if row.ops_per_s else None
            row.floor_us_per_op = 1e6 / row.floor_ops_per_s if row.floor_ops_per_s else None
            rows.append(row)
    return rows


def run_fanout(plan: Plan, loop_name: str, say: Callable[[str], None]) -> list[Result]:
    rows: list[Result] = []
    for protocol in plan.fanout_protocols:
        case = by_key(protocol)
        try:
            case.check()
        except Unavailable as exc:
            for n in plan.fanout_ns:
                rows.append(
                    Result.skipped(
                        f"fanout/{protocol}/stack", loop_name, n, str(exc), group="fanout"
                    )
                )
            continue
        for n in plan.fanout_ns:
            common = {
                "loop": loop_name,
                "repeats": plan.fanout_repeats,
                "duration": plan.fanout_duration,
                "warmup": plan.warmup,
            }
            say(f"fanout/{protocol} N={n} floor on {loop_name}")
            floor_summary = spawn(protocol, "floor", n, **common)  # type: ignore[arg-type]
            floor = series_from_summary(floor_summary)
            kinds = list(plan.fanout_kinds)
            while kinds:
                kind = kinds.pop(0)
                name = f"fanout/{protocol}/{kind}"
                say(f"{name} N={n} on {loop_name}")
                summary = spawn(protocol, kind, n, **common)  # type: ignore[arg-type]
                if "samples" not in summary:
                    note = str(summary.get("note", "no result"))
                    rows.append(Result.skipped(name, loop_name, n, note, group="fanout"))
                    unavailable = not note.startswith("child failed")
                    if kind == "poll" and unavailable and "clients" not in plan.fanout_kinds:
                        kinds.insert(0, "clients")  # no poller: still a stack number for this N
                    continue
                stack = series_from_summary(summary)
                row = Result.from_series(name, loop_name, n, stack, floor, group="fanout")
                row.p50_ms, row.p99_ms = summary.get("p50_ms"), summary.get("p99_ms")
                row.floor_p99_ms = floor_summary.get("p99_ms")
                if "note" in floor_summary:
                    row.note = f"floor: {floor_summary['note']}"
                rows.append(row)
    return rows


def run_fleet(plan: Plan, loop_name: str, say: Callable[[str], None]) -> list[Result]:
    """Floor, decoded floor and poller alternate for ``fleet_repeats`` rounds per N, in one
    child process against one set of responders (the fleet case's ``alternate``: runs of one
    round back to back, ABBA order; separate processes minutes apart differed by 15 % on a
    shared machine). CPU per request and ratio are medians over the rounds. Two rows per N:
    the poller against the raw floor (bytes), and against the floor that also turns each
    reply into its 64 ints (``decoded``, see the fleet case)."""
    rows: list[Result] = []
    name = "fleet/e71+tcp/poll"
    kinds = ("floor", "decoded", "poll")
    for n in plan.fleet_ns:
        say(
            f"fleet/e71+tcp N={n} at 10 Hz on {loop_name}: {', '.join(kinds)} alternating, "
            f"{plan.fleet_repeats} round(s)"
        )
        summary = fleet.spawn(
            "alternate",
            n,
            loop=loop_name,
            duration=plan.fleet_duration,
            warmup=plan.fleet_warmup,
            kinds=kinds,
            rounds=plan.fleet_repeats,
        )
        runs = {(run["round"], run["kind"]): run for run in summary.get("runs", ())}
        failed = summary.get("note", "")
        if not failed:
            for (r, kind), run in sorted(runs.items()):
                if not run.get("cpu_us_per_request"):
                    failed = f"{kind} (round {r + 1}): no requests completed"
                    break
        if failed or len(runs) != len(kinds) * plan.fleet_repeats:
            reason = failed or "the child reported fewer runs than asked"
            rows.append(Result.skipped(name, loop_name, n, reason, group="fleet"))
            continue
        rounds = range(plan.fleet_repeats)
        rows.append(
            fleet_row(name, loop_name, n, [(runs[r, "floor"], runs[r, "poll"]) for r in rounds])
        )
        rows.append(
            fleet_row(
                f"{name} (decoded floor)",
                loop_name,
                n,
                [(runs[r, "decoded"], runs[r, "poll"]) for r in rounds],
            )
        )
    return rows


def fleet_row(
    name: str, loop_name: str, n: int, pairs: list[tuple[dict[str, Any], dict[str, Any]]]
) -> Result:
    """One report row from (floor, stack) summaries: medians, and the ratio's range."""

    def med(side: int, key: str) -> float:
        return float(statistics.median(pair[side][key] for pair in pairs))

    ratios = sorted(f["cpu_us_per_request"] / s["cpu_us_per_request"] for f, s in pairs)
    row = Result(
        case=name,
        loop=loop_name,
        n=n,
        ops_per_s=med(1, "rate"),
        floor_ops_per_s=med(0, "rate"),
        ratio=statistics.median(ratios),
        p99_ms=med(1, "p99_ms"),
        group="fleet",
        p50_ms=med(1, "p50_ms"),
        floor_p99_ms=med(0, "p99_ms"),
        us_per_op=med(1, "cpu_us_per_request"),
        floor_us_per_op=med(0, "cpu_us_per_request"),
        repeats=len(pairs),
    )
    overruns = f"{sum(p[1]['overruns'] for p in pairs)}|{sum(p[0]['overruns'] for p in pairs)}"
    spread = f"; ratio {ratios[0]:.2f}..{ratios[-1]:.2f}" if len(ratios) > 1 else ""
    row.note = (
        f"CPU/request; target {pairs[0][1]['target']:,.0f}/s; overruns s|f {overruns}; "
        f"core s|f {med(1, 'cpu_share'):.2f}|{med(0, 'cpu_share'):.2f}{spread}"
    )
    return row


def run_peers(plan: Plan, results: list[Result], say: Callable[[str], None]) -> list[Result]:
    if not hsl_available():
        return [
            Result.skipped(
                "peer/hslcommunication",
                "-",
                0,
                "hslcommunication not installed (optional, never a dependency)",
                group="peer",
            )
        ]
    rows: list[Result] = []
    for protocol in PEER_PROTOCOLS:
        ns = [1, *plan.peer_ns]
        for n in ns:
            name = f"peer/{protocol}/hsl-threads"
            say(f"{name} N={n}")
            summary = spawn(
                protocol,
                "peer-hsl",
                n,
                loop="asyncio",
                repeats=plan.fanout_repeats,
                duration=plan.fanout_duration,
                warmup=plan.warmup,
            )
            if "samples" not in summary:
                rows.append(
                    Result.skipped(name, "threads", n, str(summary.get("note")), group="peer")
                )
                continue
            row = Result.from_series(
                name, "threads", n, series_from_summary(summary), None, group="peer"
            )
            row.p50_ms, row.p99_ms = summary.get("p50_ms"), summary.get("p99_ms")
            # the floor of the same N (asyncio loop) from the fan-out or one-connection rows
            floors = [
                r.floor_ops_per_s
                for r in results
                if r.loop == "asyncio"
                and r.n == n
                and r.floor_ops_per_s
                and f"/{protocol}/" in r.case
                and r.group in ("fanout", "conn")
                and (r.group == "fanout" or r.case.endswith(f"read{WORDS}"))
            ]
            if floors and row.ops_per_s is not None:
                row.floor_ops_per_s = statistics.median(floors)
                row.ratio = row.ops_per_s / row.floor_ops_per_s
            rows.append(row)
    return rows
