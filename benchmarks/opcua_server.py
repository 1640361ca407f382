"""The OPC UA server under load: 1000 tags at 1 Hz, latency from a PLC change to the client.

Setup: E71 simulators in this process (``--plcs`` PLCs of ``--tags`` uint16 tags each, D0..), a
``plcstack serve opcua`` child process polling them every ``--interval`` seconds and serving them,
and one asyncua client in this process subscribed to every tag (publishing interval
``--publish`` ms). Every tag's register changes once per ``--change-every`` seconds, spread
evenly; each change writes a new value, and its notification's arrival is matched to the moment
of the write.

Measured:

* latency, PLC memory change -> client notification (p50/p99/max/mean). Most of it is the poll:
  a change waits for the next read of its tag, on average half a scan interval, then up to one
  publishing interval;
* latency, the poller's read request (the notification's SourceTimestamp) -> client
  notification: the PLC round trip, the poller, the server and the wait for the next publish;
  what serving over OPC UA adds after the read (same machine, same wall clock);
* the server process's CPU over the measuring window (user + system, from /proc), in % of one
  core: poller, OPC UA server and subscription together, i.e. what ``plcstack serve opcua`` costs;
* notifications matched vs changes made: below 100 % only when a tag changed twice between two
  reads of it (timer jitter when ``--change-every`` equals ``--interval``), since the poller
  then sees the last value only.

    python -m benchmarks.opcua_server [--plcs 10] [--tags 100] [--interval 1.0] [--seconds 20]
    python -m benchmarks.opcua_server --poll-only     # the same polling without the server
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from plcstack.sim import e71 as sim_e71
from plcstack.sim.melsec_memory import MelsecMemory

ROOT = Path(__file__).resolve().parent.parent


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks  # utime, stime (fields 14, 15)


def write_config(path: Path, urls: list[str], tags: int, interval: float) -> None:
    lines = [f"[poll]\ninterval = {interval}\n", '[opcua]\nlisten = "127.0.0.1:0"\npath = "/b"\n']
    for i, url in enumerate(urls):
        lines.append(f'[[plc]]\nname = "plc{i}"\nurl = "{url}"\n[plc.tags]')
        lines.extend(f't{j} = {{ address = "D{j}", type = "uint16" }}' for j in range(tags))
        lines.append("")
    path.write_text("\n".join(lines), encoding="utf-8")


class Handler:
    """Matches each notification to the change that caused it: (plc, tag, value) -> t."""

    def __init__(self, names: dict[Any, tuple[int, int]]) -> None:
        self.names = names
        self.changed: dict[tuple[int, int, int], float] = {}
        self.latencies: list[float] = []
        #: SourceTimestamp (the poller sent the read) -> notification: poller + server + publish
        self.after_read: list[float] = []
        self.notifications = 0
        #: changes made from this moment on are measured
        self.since = float("inf")

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        now = time.perf_counter()
        wall = time.time()
        self.notifications += 1
        key = (*self.names[node.nodeid], val)
        t = self.changed.pop(key, None)
        if t is not None and t >= self.since:
            self.latencies.append(now - t)
            source = data.monitored_item.Value.SourceTimestamp
            if source is not None:
                self.after_read.append(wall - source.timestamp())


async def change_loop(
    memories: list[MelsecMemory], tags: int, every: float, handler: Handler, stop: float
) -> int:
    """Write a new value to every tag once per ``every`` seconds on average, in 20 slices.

    The slices come at random moments (uniform gaps averaging ``every / 20``), so a change lands
    at a random phase of the poller's scan, as a real process value does.
    """
    slices = 20
    cells = [(p, t) for p in range(len(memories)) for t in range(tags)]
    per_slice = max(1, len(cells) // slices)
    value = 1
    changes = 0
    next_at = time.perf_counter()
    while time.perf_counter() < stop:
        for start in range(0, len(cells), per_slice):
            now = time.perf_counter()
            for p, t in cells[start : start + per_slice]:
                memories[p].write_words("D", t, [value])
                handler.changed[(p, t, value)] = now
                changes += now >= handler.since
            next_at += random.uniform(0.0, 2.0 * every / slices)
            await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
        value = value % 65535 + 1
    return changes


async def main_async(args: argparse.Namespace) -> None:
    memories = [MelsecMemory() for _ in range(args.plcs)]
    sims = [await sim_e71.start(m) for m in memories]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            config = Path(tmp) / "bench.toml"
            write_config(config, [s.url for s in sims], args.tags, args.interval)
            if args.poll_only:
                await poll_only(args, memories, config)
            else:
                await serve(args, memories, config)
    finally:
        for sim in sims:
            await sim.aclose()


async def serve(args: argparse.Namespace, memories: list[MelsecMemory], config: Path) -> None:
    from asyncua.client.client import Client

    proc = await asyncio.create_subprocess_exec(
        *(sys.executable, "-m", "plcstack", "serve", "opcua", str(config)),
        stderr=asyncio.subprocess.PIPE,
        cwd=ROOT,
    )
    try:
        assert proc.stderr is not None
        while b"listening on" not in (line := await proc.stderr.readline()):
            if not line:
                raise SystemExit("the server ended before listening")
        url = line.decode().rsplit(" ", 1)[1].strip()
        async with Client(url, timeout=30) as client:
            idx = await client.get_namespace_index("urn:plcstack")
            names: dict[Any, tuple[int, int]] = {}
            nodes = []
            for p in range(args.plcs):
                for t in range(args.tags):
                    node = client.get_node(f"ns={idx};s=plc{p}.t{t}")
                    names[node.nodeid] = (p, t)
                    nodes.append(node)
            handler = Handler(names)
            sub = await client.create_subscription(args.publish, handler)
            for i in range(0, len(nodes), 500):
                await sub.subscribe_data_change(nodes[i : i + 500])
            changes, cpu = await measure(args, memories, handler, proc.pid)
            await asyncio.sleep(args.interval + 1.0)  # the last changes' notifications
        report(args, handler, changes, cpu)
    finally:
        await stop(proc)


async def poll_only(args: argparse.Namespace, memories: list[MelsecMemory], config: Path) -> None:
    """The baseline: ``plcstack poll`` of the same PLCs and changes, JSON lines to /dev/null."""
    proc = await asyncio.create_subprocess_exec(
        *(sys.executable, "-m", "plcstack", "poll", str(config)),
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.DEVNULL,
        cwd=ROOT,
    )
    try:
        _, cpu = await measure(args, memories, Handler({}), proc.pid)
        tags = args.plcs * args.tags
        print(
            f"baseline plcstack poll (JSON lines to /dev/null), {tags} tags every "
            f"{args.interval} s: CPU {cpu * 100:.1f} % of one core"
        )
    finally:
        await stop(proc)


async def measure(
    args: argparse.Namespace, memories: list[MelsecMemory], handler: Handler, pid: int
) -> tuple[int, float]:
    """Change the PLCs' memory through warm-up and window; returns (changes, CPU share of pid)."""
    warm = time.perf_counter() + args.warmup
    end = warm + args.seconds
    changer = asyncio.create_task(change_loop(memories, args.tags, args.change_every, handler, end))
    await asyncio.sleep(max(0.0, warm - time.perf_counter()))
    handler.since = time.perf_counter()
    cpu0, t0 = cpu_seconds(pid), time.perf_counter()
    changes = await changer
    cpu1, t1 = cpu_seconds(pid), time.perf_counter()
    return changes, (cpu1 - cpu0) / (t1 - t0)


async def stop(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is None:
        proc.terminate()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(proc.wait(), 10)


def report(args: argparse.Namespace, handler: Handler, changes: int, cpu: float) -> None:
    lat = sorted(handler.latencies)
    after = sorted(handler.after_read)
    tags = args.plcs * args.tags
    print(
        f"{tags} tags ({args.plcs} PLCs x {args.tags}) polled every {args.interval} s, "
        f"every tag changed every {args.change_every} s, publishing interval {args.publish} ms"
    )
    if not lat:
        print("no notification matched a change")
        return

    def line(what: str, data: list[float]) -> str:
        def pct(q: float) -> float:
            return data[min(len(data) - 1, int(q * len(data)))] * 1000

        return (
            f"{what}: p50 {pct(0.5):.0f} ms, p99 {pct(0.99):.0f} ms, "
            f"max {data[-1] * 1000:.0f} ms, mean {statistics.fmean(data) * 1000:.0f} ms"
        )

    print(line("latency PLC change -> client notification", lat))
    if after:
        print(line("latency poller's read sent (SourceTimestamp) -> client notification", after))
    print(f"notifications matched {len(lat)} of {changes} changes made while measuring")
    rate = changes / args.seconds
    print(
        f"server process CPU: {cpu * 100:.1f} % of one core "
        f"({cpu * 1e6 / tags:.0f} us per tag and second, {rate:.0f} changes/s)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plcs", type=int, default=10)
    parser.add_argument("--tags", type=int, default=100, help="tags per PLC")
    parser.add_argument("--interval", type=float, default=1.0, help="scan interval (s)")
    parser.add_argument(
        "--change-every", type=float, default=2.0, help="each tag changes every S s on average"
    )
    parser.add_argument("--publish", type=float, default=100.0, help="publishing interval (ms)")
    parser.add_argument("--seconds", type=float, default=20.0, help="measuring window")
    parser.add_argument("--warmup", type=float, default=3.0)
    parser.add_argument(
        "--poll-only", action="store_true", help="baseline: plcstack poll instead of the server"
    )
    asyncio.run(main_async(parser.parse_args()))


if __name__ == "__main__":
    main()
