"""The embedded history's costs: CPU and disk at 10,000 changing tags a second, and a day's query.

**write** (default): 1000 PLCs in another process (the PLC process of
``benchmarks.web_console``: one listening socket, 1000 connections, every word changing every
second), polled at 1 Hz by a real :class:`~plcstack.poll.engine.Poller` in this process: 15
words per PLC read as 5 ``int16`` and 5 ``float32`` tags, so 10,000 tags change every second.
The :class:`~plcstack.north.pipeline.North` consumer feeds a :class:`~plcstack.north.history.
History` in a temporary directory. Modes in turns (``--rounds``, ``--window`` seconds each,
after 2 s to settle): ``poller`` (the history is not among the sinks) and ``history``. Figures:

* process CPU time (``time.process_time``: every thread) per second of wall time, by mode;
  the history's share = the difference of the medians;
* the writer thread's own CPU time (``time.thread_time`` around each of its rounds, so
  checkpoints included) per sample taken: the same cost, without the machine's noise;
* bytes on disk per stored point after the run (the file's pages in use, and the file's size);
* write lag: seconds from a sample's arrival to the commit of its journal row, per round.

**query**: a history of 20 tags at 1 Hz over one day, written as the writer writes it at
10,000 tags a second (a block per tag every 100 points), then one tag's day downsampled to 1000
points: :meth:`History.query` and ``GET /api/history`` through the web console (aiohttp client
on loopback), median and maximum of ``--repeat`` answers.

    python -m benchmarks.history [write|query|both] [--plcs 1000] [--window 30] [--rounds 4]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import statistics
import struct
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from benchmarks.web_console import all_answered, finish, ready, start_helper, window
from plcstack.bench.cases.fanout import raise_fd_limit
from plcstack.north.config import NorthConfig
from plcstack.north.history import History, HistorySettings
from plcstack.north.history.writer import Writer
from plcstack.north.pipeline import North
from plcstack.output import float32_short
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Scan, make_sample
from plcstack.values import FLOAT32, INT16

MODES = ("poller", "history")


class TimedWriter(Writer):
    """The writer, with the CPU time of its thread counted around each round."""

    cpu = 0.0
    lags: list[float]

    def write(self, batches: Sequence[Sequence[Scan]], *, final: bool = False) -> None:
        start = time.thread_time()
        try:
            super().write(batches, final=final)
        finally:
            self.cpu += time.thread_time() - start
            if batches:
                self.lags.append(self.stats.lag)


def disk(path: Path) -> dict[str, float]:
    import sqlite3

    db = sqlite3.connect(path)
    try:
        pages, free, size = (
            db.execute(f"PRAGMA {p}").fetchone()[0]
            for p in ("page_count", "freelist_count", "page_size")
        )
        points, blocks, data = db.execute(
            "SELECT SUM(n), COUNT(*), SUM(LENGTH(data)) FROM blocks"
        ).fetchone()
    finally:
        db.close()
    return {
        "points": points,
        "blocks": blocks,
        "points_per_block": points / blocks,
        "bytes_in_use": (pages - free) * size,
        "file_bytes": path.stat().st_size,
        "bytes_per_point_in_use": (pages - free) * size / points,
        "bytes_per_point_file": path.stat().st_size / points,
        "bytes_per_point_blobs": data / points,
    }


async def measure_write(args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    raise_fd_limit(args.plcs * 2 + 256)
    words = 15
    plcs = start_helper("plcs", str(words))
    port = json.loads(ready(plcs, "the PLC process"))["port"]
    tags = tuple(TagConfig(f"i{i}", f"D{i}", INT16) for i in range(5)) + tuple(
        TagConfig(f"f{i}", f"D{5 + 2 * i}", FLOAT32) for i in range(5)
    )
    config = PollConfig(
        tuple(
            PlcConfig(f"plc{i:04d}", f"e71+tcp://127.0.0.1:{port}", tags) for i in range(args.plcs)
        ),
        {"default": 1.0},
    )
    settings = HistorySettings(path=folder / "history.sqlite")
    writer = TimedWriter(settings)
    writer.lags = []
    poller = Poller(config)
    north = North(poller, NorthConfig())
    history = History(settings, writer=writer, supervisor=north.supervisor)
    cpu: dict[str, list[float]] = {m: [] for m in MODES}
    rates: dict[str, list[float]] = {m: [] for m in MODES}
    try:
        async with poller, north:
            await history.start()
            consumer = asyncio.create_task(north.run())
            await all_answered(poller)
            for r in range(args.rounds):
                for mode in MODES[r % 2 :] + MODES[: r % 2]:
                    if mode == "poller":
                        north.faces = [f for f in north.faces if f is not history]
                    elif history not in north.faces:
                        north.faces.append(history)
                    share, rate = await window(poller, args.window)
                    cpu[mode].append(share)
                    rates[mode].append(rate)
                    print(
                        f"round {r + 1} {mode:8s} cpu {cpu[mode][-1] * 100:5.1f} % of a core,"
                        f" {rates[mode][-1]:6.0f} requests/s, writer {writer.stats}",
                        file=sys.stderr,
                        flush=True,
                    )
            consumer.cancel()
            await asyncio.gather(consumer, return_exceptions=True)
            await history.aclose()
    finally:
        finish(plcs)
    base = statistics.median(cpu["poller"])
    stats = writer.stats
    lags = sorted(writer.lags)
    return {
        "plcs": args.plcs,
        "tags": args.plcs * len(tags),
        "window_s": args.window,
        "rounds": args.rounds,
        "cpu_share_of_a_core": {m: statistics.median(v) for m, v in cpu.items()},
        "requests_per_s": {m: statistics.median(v) for m, v in rates.items()},
        "history_share_of_a_core_by_difference": statistics.median(cpu["history"]) - base,
        "writer_thread_us_per_sample": writer.cpu / stats.taken * 1e6,
        "writer_thread_share_at_10000_per_s": writer.cpu / stats.taken * 10_000,
        "samples_taken": stats.taken,
        "checkpoints": stats.checkpoints,
        "dropped": stats.dropped + history.dropped,
        "write_lag_s": {"median": statistics.median(lags), "max": lags[-1]},
        "disk": disk(settings.path),
    }


def _f32(x: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", x))[0])


async def measure_query(args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    from aiohttp import ClientSession

    from plcstack.north.web.server import WebConsole
    from plcstack.north.web.settings import WebSettings

    day, tags = 86_400, 20
    end = time.time()
    start = end - day
    settings = HistorySettings(path=folder / "query.sqlite")
    # a block per tag every 100 points, as at 10,000 tags a second (1,000,000 open points)
    writer = Writer(settings, max_open_points=tags * 100, clock=lambda: end)
    writer.open()
    began = time.perf_counter()
    for second in range(0, day, 10):
        scans = []
        for s in range(second, second + 10):
            t = start + s
            value = _f32(60 + 15 * math.sin(s / 3000) + (s % 17) / 10)
            samples = tuple(
                make_sample("press", f"t{k}", value + k, Quality.GOOD, t, t + 0.005, None)
                for k in range(tags)
            )
            scans.append(Scan("press", "default", t, t + 0.005, samples))
        writer.write([scans])
    writer.close()
    written = time.perf_counter() - began
    tag = TagConfig("t3", "D0", FLOAT32)
    poller = Poller(PollConfig((PlcConfig("press", "e71+tcp://127.0.0.1:1", (tag,)),)))
    history = History(settings, clock=lambda: end)
    await history.start()
    console = WebConsole(poller, WebSettings(port=0), history=history)
    await console.start()
    direct, http, cpu = [], [], []
    try:
        for _ in range(args.repeat):
            c0, t0 = time.process_time(), time.perf_counter()
            points = await history.query("press", "t3", start, end, 1000)
            direct.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        url = f"{console.url}api/history?plc=press&tag=t3&from={start}&to={end}&points=1000"
        async with ClientSession() as session:
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                async with session.get(url) as response:
                    body = await response.read()
                http.append(time.perf_counter() - t0)
        answer = json.loads(body)["points"]
    finally:
        await console.aclose()
        await history.aclose()
    numbers = [float(v) for _, v in points if isinstance(v, int | float)]
    assert len(numbers) == len(points), "the float32 tag's points are numbers"
    return {
        "points_in_the_day": day,
        "blocks_of_the_tag": day // 100,
        "points_answered": len(answer),
        "answer_bytes": len(body),
        "write_s_for_the_file": written,
        "query_ms": {"median": statistics.median(direct) * 1e3, "max": max(direct) * 1e3},
        "query_cpu_ms": statistics.median(cpu) * 1e3,
        "http_ms": {"median": statistics.median(http) * 1e3, "max": max(http) * 1e3},
        "extremes_kept": (
            max(v for _, v in answer) == float32_short(max(numbers))
            and min(v for _, v in answer) == float32_short(min(numbers))
        ),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.history")
    parser.add_argument("what", nargs="?", default="both", choices=("write", "query", "both"))
    parser.add_argument("--plcs", type=int, default=1000)
    parser.add_argument("--window", type=float, default=30.0)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args(argv)
    result: dict[str, Any] = {"load_before": os.getloadavg(), "cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="plcstack-history-bench-") as tmp:
        if args.what in ("write", "both"):
            result["write"] = asyncio.run(measure_write(args, Path(tmp)))
        if args.what in ("query", "both"):
            result["query"] = asyncio.run(measure_query(args, Path(tmp)))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
