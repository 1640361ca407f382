"""Figures of the scale-out (issue 18): takeover time, broker traffic, each worker's added CPU.

Starts mosquitto and nats-server (JetStream) on free loopback ports, a fleet of E71 simulators in
this process, and worker processes (``python -m plcstack poll``). Three phases:

1. static: ``--shard i/N`` workers over the fleet, CPU of each over ``--window`` seconds;
2. automatic: ``--mqtt`` workers (presence only), then ``--mqtt --nats`` workers over the same
   fleet (same assignment: rendezvous hashing over the same number of workers), CPU and broker
   messages over the same window; the difference of CPU is what the leases add;
3. failover: ``kill -9`` one worker; for each of its PLCs, the time until a simulator sees the
   next request; peak concurrent connections of every simulator over the whole run.

    python -m benchmarks.scale_failover [--plcs 300] [--workers 3] [--interval 0.1]
        [--ttl 10] [--retry 1] [--window 15] [--json out.json]

Needs mosquitto and nats-server (Debian packages) and a checkout (it uses ``tests/servers.py``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiomqtt

from plcstack.scale.hrw import owner
from plcstack.scale.lease import LeaseStore, lease_key
from tests.scale_helpers import Fleet, WorkerProcess
from tests.servers import Mosquitto, NatsServer


def shard_command(proc: WorkerProcess, index: int, count: int) -> None:
    """Turn an automatic-mode command into the static ``--shard index/count`` one."""
    base = proc.command[: proc.command.index("--mqtt")]
    proc.command = [*base, "--shard", f"{index}/{count}"]


async def cpu_over(procs: list[WorkerProcess], seconds: float) -> list[float]:
    """Each process's CPU use in percent of one core over ``seconds``."""
    before = [p.cpu_seconds() for p in procs]
    await asyncio.sleep(seconds)
    after = [p.cpu_seconds() for p in procs]
    return [round(100 * (b - a) / seconds, 1) for a, b in zip(before, after, strict=True)]


class MqttCounter:
    """mosquitto's own ``$SYS`` counters of PUBLISH messages (sys_interval 1 s)."""

    def __init__(self, broker: Mosquitto) -> None:
        self.broker = broker
        self.values: dict[str, int] = {}
        self.task: asyncio.Task[None] | None = None

    async def run(self) -> None:
        async with aiomqtt.Client(self.broker.host, self.broker.port) as client:
            await client.subscribe("$SYS/broker/publish/messages/+")
            await client.subscribe("$SYS/broker/messages/+")
            async for message in client.messages:
                with contextlib.suppress(TypeError, ValueError):
                    self.values[str(message.topic)] = int(bytes(message.payload).decode())

    def snapshot(self) -> dict[str, int]:
        return dict(self.values)


async def wait_holders(
    store: LeaseStore, plcs: list[str], workers: list[str], timeout: float
) -> None:
    expected = {lease_key(p): owner(p, workers) for p in plcs}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if await store.holders() == expected:
            return
        await asyncio.sleep(0.2)
    raise SystemExit("the leases never matched rendezvous hashing; see the worker logs")


async def main(args: argparse.Namespace) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="plcstack-scale-bench-"))
    broker = Mosquitto(persistence=False, extra_config="sys_interval 1")
    nats_server = NatsServer()
    broker.start()
    nats_server.start()
    result: dict[str, Any] = {
        "plcs": args.plcs,
        "workers": args.workers,
        "interval_s": args.interval,
        "ttl_s": args.ttl,
        "retry_s": args.retry,
        "window_s": args.window,
    }
    names = [f"w{i + 1}" for i in range(args.workers)]
    counter = MqttCounter(broker)
    try:
        async with Fleet(args.plcs, interval=args.interval, every=0.01) as fleet:
            config = fleet.toml(tmp / "fleet.toml", timeout=2.0)
            plcs = list(fleet.watch)
            counter.task = asyncio.get_running_loop().create_task(counter.run())

            def workers() -> list[WorkerProcess]:
                return [
                    WorkerProcess(
                        n,
                        config,
                        mqtt=broker.url,
                        nats=nats_server.url,
                        ttl=args.ttl,
                        retry=args.retry,
                        keepalive=5,
                        logdir=tmp,
                    )
                    for n in names
                ]

            # 1. static shards
            static = workers()
            for i, p in enumerate(static):
                shard_command(p, i, args.workers)
                p.start()
            await asyncio.sleep(3)
            n0 = fleet.requests()
            result["cpu_static_pct"] = await cpu_over(static, args.window)
            result["requests_per_s_static"] = round((fleet.requests() - n0) / args.window)
            for p in static:
                p.stop()
            print(
                f"static:    CPU % {result['cpu_static_pct']}, "
                f"{result['requests_per_s_static']} requests/s",
                file=sys.stderr,
            )

            # 2a. automatic mode, presence only (no leases): what the worker loop itself costs
            bare = workers()
            for p in bare:
                p.command = [c for c in p.command if c not in ("--nats", nats_server.url)]
                p.start()
            await asyncio.sleep(5)
            n0 = fleet.requests()
            result["cpu_presence_only_pct"] = await cpu_over(bare, args.window)
            result["requests_per_s_presence_only"] = round((fleet.requests() - n0) / args.window)
            for p in bare:
                p.stop()
            # without leases, a PLC may have two pollers while ownership settles
            result["presence_only_max_concurrent_connections"] = max(fleet.peaks().values())
            print(
                f"presence only: CPU % {result['cpu_presence_only_pct']}, "
                f"{result['requests_per_s_presence_only']} requests/s",
                file=sys.stderr,
            )
            await asyncio.sleep(1)

            # 2b. automatic mode with leases
            await asyncio.sleep(0.5)
            fleet.reset_peaks()
            auto = workers()
            for p in auto:
                p.start()
            observer = LeaseStore(nats_server.url, worker="bench", ttl=args.ttl)
            await asyncio.sleep(2)
            await observer.connect()
            await wait_holders(observer, plcs, names, 60)
            await asyncio.sleep(args.ttl / 2)  # past the start-up moves
            varz0, mqtt0 = nats_server.varz(), counter.snapshot()
            n0 = fleet.requests()
            result["cpu_auto_pct"] = await cpu_over(auto, args.window)
            result["requests_per_s_auto"] = round((fleet.requests() - n0) / args.window)
            varz1, mqtt1 = nats_server.varz(), counter.snapshot()
            added = [
                round(a - s, 1)
                for a, s in zip(
                    result["cpu_auto_pct"], result["cpu_presence_only_pct"], strict=True
                )
            ]
            result["cpu_added_by_leases_pct"] = added
            nats_in = (int(str(varz1["in_msgs"])) - int(str(varz0["in_msgs"]))) / args.window
            nats_out = (int(str(varz1["out_msgs"])) - int(str(varz0["out_msgs"]))) / args.window
            result["nats_msgs_per_s"] = {"in": round(nats_in, 1), "out": round(nats_out, 1)}
            result["mqtt_per_s"] = {
                k.removeprefix("$SYS/broker/"): round((mqtt1[k] - mqtt0.get(k, 0)) / args.window, 2)
                for k in sorted(mqtt1)
            }
            print(
                f"automatic: CPU % {result['cpu_auto_pct']} (leases add {added}), "
                f"{result['requests_per_s_auto']} requests/s",
                file=sys.stderr,
            )
            print(f"NATS msgs/s {result['nats_msgs_per_s']}", file=sys.stderr)
            print(f"MQTT /s {result['mqtt_per_s']}", file=sys.stderr)

            # 3. kill -9 one worker
            loop = asyncio.get_running_loop()
            victim = auto[0]
            orphans = [p for p in plcs if owner(p, names) == victim.name]
            killed = loop.time()
            victim.kill()
            await fleet.wait_all_polled(killed, timeout=args.ttl + 30)
            deadline = loop.time() + args.ttl + 30
            while any(fleet.reconnected_after(killed)[p] is None for p in orphans):
                assert loop.time() < deadline, "orphans not taken over"
                await asyncio.sleep(0.1)
            first = fleet.reconnected_after(killed)
            times = sorted(first[p] - killed for p in orphans if first[p] is not None)  # type: ignore[operator]
            result["takeover_s"] = {
                "orphans": len(orphans),
                "min": round(times[0], 3),
                "median": round(statistics.median(times), 3),
                "max": round(times[-1], 3),
            }
            print(f"takeover after kill -9: {result['takeover_s']}", file=sys.stderr)
            await wait_holders(observer, plcs, names[1:], 30)
            victim.start()
            back = loop.time()
            await wait_holders(observer, plcs, names, 60)
            result["return_s"] = round(loop.time() - back, 2)
            peaks = fleet.peaks()
            # from the start of the workers with leases, through the kill and the return
            result["leases_max_concurrent_connections"] = max(peaks.values())
            print(f"peak connections per PLC: {max(peaks.values())}", file=sys.stderr)
            for p in auto:
                p.stop()
            await observer.close()
    finally:
        if counter.task is not None:
            counter.task.cancel()
            await asyncio.gather(counter.task, return_exceptions=True)
        broker.close()
        nats_server.close()
    result["logs"] = str(tmp)
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--plcs", type=int, default=300)
    parser.add_argument("--workers", type=int, default=3)
    parser.add_argument("--interval", type=float, default=0.1)
    parser.add_argument("--ttl", type=float, default=10.0)
    parser.add_argument("--retry", type=float, default=1.0)
    parser.add_argument("--window", type=float, default=15.0)
    parser.add_argument("--json", default=None)
    arguments = parser.parse_args()
    out = asyncio.run(main(arguments))
    text = json.dumps(out, indent=2)
    print(text)
    if arguments.json:
        Path(arguments.json).write_text(text + "\n")
