"""A reload of a running fleet: 1000 E71 PLCs polled at 1 Hz; 10 added, 10 removed and the tags
of 10 changed, first by SIGHUP, then by ``ConfigControl.replace`` (what ``POST /api/config``
does); then a file that does not load.

The PLCs are the fleet case's fixed-reply responders (``plcstack.bench.cases.fleet``: every
12-byte request answered with the same 130-byte 64-word reply) in a process of their own on the
last CPU; this process runs the runtime as ``plcstack poll`` does (``run_north``: the poller, the
north side, the signal handlers, the reload path) pinned to CPU 0, with one face of its own that
notes when each PLC's samples arrive.

Reported: the time each apply took (from the signal or the call until the reload's line), for
the 970 PLCs that stay unchanged throughout their reconnects (0 asked) and the largest gap
between two of their samples across the whole run (at most 2 intervals asked), the process's
CPU per second before and after each apply (``time.process_time`` over a window), and what a
file that does not load changed (nothing asked)::

    python -m benchmarks.reload [--plcs 1000] [--window 5]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import signal
import sys
import tempfile
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from plcstack.bench.cases.fanout import raise_fd_limit
from plcstack.bench.cases.fleet import _start_responders
from plcstack.cli.reload import RuntimeControl
from plcstack.cli.runtime import run_north
from plcstack.north.face import FaceBase
from plcstack.north.pipeline import North
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Scan

INTERVAL = 1.0
STEP = 10


class Arrivals(FaceBase):
    """When each PLC's scans arrive, and the largest gap between two of them so far."""

    name = "arrivals"

    def __init__(self) -> None:
        self.last: dict[str, float] = {}
        self.gap: dict[str, float] = {}
        #: the largest gap of the whole run, never cleared
        self.worst: dict[str, float] = {}

    def submit(self, scans: Sequence[Scan]) -> None:
        now = time.monotonic()
        last, gap = self.last, self.gap
        for scan in scans:
            before = last.get(scan.plc)
            if before is not None:
                if now - before > gap.get(scan.plc, 0.0):
                    gap[scan.plc] = now - before
                if now - before > self.worst.get(scan.plc, 0.0):
                    self.worst[scan.plc] = now - before
            last[scan.plc] = now


def _plc(i: int, port: int, typed: bool) -> str:
    kind = ', type = "int16"' if typed else ""
    return (
        f'[[plc]]\nname = "p{i:04d}"\nurl = "e71+tcp://127.0.0.1:{port}"\n'
        f'[plc.tags]\nw = {{ address = "D0", count = 64{kind} }}\n'
    )


def _text(ports: Sequence[int], plcs: Sequence[int], typed: set[int]) -> str:
    head = f"[poll]\ninterval = {INTERVAL}\ntimeout = 3.0\n"
    return head + "".join(_plc(i, ports[i], i in typed) for i in plcs)


class Reloads(logging.Handler):
    """The reload lines, with when they were said."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[tuple[float, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((time.monotonic(), record.getMessage()))


async def _cpu(seconds: float) -> float:
    """This process's CPU seconds per second over the next ``seconds``."""
    cpu, wall = time.process_time(), time.monotonic()
    await asyncio.sleep(seconds)
    return (time.process_time() - cpu) / (time.monotonic() - wall)


def _unchanged(
    out: dict[str, object], what: str, poller: Poller, arrivals: Arrivals, plcs: Iterable[int]
) -> None:
    """The PLCs one apply left unchanged: how many, their reconnects since the start, and the
    largest gap between two of their samples since just before the apply."""
    names = [f"p{i:04d}" for i in plcs]
    stats = poller.stats
    gap = max(arrivals.gap[p] for p in names)
    out[f"{what}: unchanged PLCs, reconnects, connect failures, largest gap (intervals)"] = (
        len(names),
        sum(stats[p].reconnects for p in names),
        sum(stats[p].connect_failures for p in names),
        round(gap / INTERVAL, 2),
    )


async def _wait_line(reloads: Reloads, count: int, since: float) -> float:
    while len(reloads.lines) < count:  # noqa: ASYNC110 - the reload runs in the runtime's task
        await asyncio.sleep(0.001)
    return reloads.lines[count - 1][0] - since


async def _steps(
    path: Path,
    ports: Sequence[int],
    n: int,
    control: RuntimeControl,
    poller: Poller,
    arrivals: Arrivals,
    reloads: Reloads,
    window: float,
) -> dict[str, object]:
    out: dict[str, object] = {}
    first = list(range(n))
    async with asyncio.timeout(120):
        while len(arrivals.last) < n or min(poller.stats[p].scans for p in poller.plcs) < 3:  # noqa: ASYNC110
            await asyncio.sleep(0.2)
    arrivals.gap.clear()  # from here on: the start's connects are over
    arrivals.worst.clear()
    out["cpu before"] = await _cpu(window)
    # the same figures with no reload at all: what the machine's own stalls cost
    _unchanged(out, "no reload", poller, arrivals, range(4 * STEP, n))
    arrivals.gap.clear()  # the gaps around the first apply
    # 1. SIGHUP: p0000-p0009 removed, p{n}..p{n+9} added, p0010-p0019 typed (replanned)
    second = [*first[STEP:], *range(n, n + STEP)]
    path.write_text(_text(ports, second, set(range(STEP, 2 * STEP))))  # noqa: ASYNC240
    start = time.monotonic()
    os.kill(os.getpid(), signal.SIGHUP)
    out["apply by SIGHUP (s)"] = await _wait_line(reloads, 1, start)
    out["line 1"] = reloads.lines[0][1]
    out["cpu after SIGHUP"] = await _cpu(window)
    _unchanged(out, "SIGHUP", poller, arrivals, range(2 * STEP, n))
    # 2. replace: p0020-p0029 removed, p{n+10}..p{n+19} added, p0030-p0039 typed
    third = [i for i in second if not 2 * STEP <= i < 3 * STEP]
    third += range(n + STEP, n + 2 * STEP)
    typed = set(range(STEP, 2 * STEP)) | set(range(3 * STEP, 4 * STEP))
    arrivals.gap.clear()  # the gaps around the second apply
    start = time.monotonic()
    outcome = await control.replace(_text(ports, third, typed), who="web 127.0.0.1 (bench)")
    out["apply by replace (s)"] = time.monotonic() - start
    out["line 2"] = outcome.summary
    out["cpu after replace"] = await _cpu(window)
    _unchanged(
        out, "replace", poller, arrivals, [*range(STEP, 2 * STEP), *range(4 * STEP, n + STEP)]
    )
    # 3. a file that does not load
    arrivals.gap.clear()
    plcs_before = list(poller.plcs)
    path.write_text(_text(ports, third, typed) + '[[plc]]\nname = "broken"\n')  # noqa: ASYNC240
    start = time.monotonic()
    refused = control.refused
    os.kill(os.getpid(), signal.SIGHUP)
    while control.refused == refused:  # noqa: ASYNC110
        await asyncio.sleep(0.001)
    out["refusal (s)"] = time.monotonic() - start
    out["after a broken file: PLCs as before"] = poller.plcs == plcs_before
    out["cpu after the broken file"] = await _cpu(window)
    _unchanged(out, "broken file", poller, arrivals, range(4 * STEP, n + 2 * STEP))
    # unchanged through both applies and the broken file, from the end of the start on
    arrivals.gap = arrivals.worst
    _unchanged(out, "throughout", poller, arrivals, range(4 * STEP, n))
    stats = poller.stats
    added = [f"p{i:04d}" for i in range(n, n + 2 * STEP)]
    out["added PLCs scanning"] = sum(1 for p in added if stats[p].scans > 0)
    out["removed PLCs still polled"] = sum(
        1 for i in range(STEP) if f"p{i:04d}" in poller.plcs
    ) + sum(1 for i in range(2 * STEP, 3 * STEP) if f"p{i:04d}" in poller.plcs)
    out["reloads applied, refused"] = (control.applied, control.refused)
    return out


async def _run(n: int, window: float) -> dict[str, object]:
    cpus = sorted(os.sched_getaffinity(0))
    responders, ports = _start_responders(n + 2 * STEP, cpus[-1] if len(cpus) > 1 else None)
    if len(cpus) > 1:
        os.sched_setaffinity(0, {cpus[0]})
    # the fleet's PLCs share the responders' listening ports: the loader's notice that an E71
    # takes 8 connections is true of a real E71, not of these responders
    logging.getLogger("plcstack.config").setLevel(logging.ERROR)
    reloads = Reloads()
    logging.getLogger("plcstack.reload").addHandler(reloads)
    logging.getLogger("plcstack.reload").setLevel(logging.INFO)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "fleet.toml"
            path.write_text(_text(ports, range(n), set()))
            control = RuntimeControl.load(path)
            poller = Poller(control.config.poll)
            arrivals = Arrivals()
            north = North(poller, control.config.north, faces=[arrivals], control=control)
            result: dict[str, object] = {}

            async def steps() -> None:
                try:
                    result.update(
                        await _steps(path, ports, n, control, poller, arrivals, reloads, window)
                    )
                finally:
                    os.kill(os.getpid(), signal.SIGTERM)  # the run ends as a service's does

            task = asyncio.create_task(steps())
            with open(os.devnull, "w") as null, contextlib.redirect_stderr(null):  # noqa: ASYNC230
                code = await run_north("bench", control, poller, north, duration=None, out=null)
            await task
            result["exit"] = code
            return result
    finally:
        assert responders.stdin is not None
        responders.stdin.close()
        responders.wait(10)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plcs", type=int, default=1000)
    parser.add_argument("--window", type=float, default=5.0, help="seconds of each CPU window")
    args = parser.parse_args(argv)
    raise_fd_limit(2 * args.plcs + 200)
    result = asyncio.run(_run(args.plcs, args.window))
    json.dump(result, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
