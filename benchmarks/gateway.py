"""Requests/s and latency through the AS511 gateway at emulated 9600 baud, against the line rate.

The AS511 simulator emulates a 9600 baud 8E1 line (every chunk delayed by 11 bits per byte). The
gateway's AS511 client counts the bytes it sends and receives; the line-rate limit of a request
is that count times 11 / 9600 s: the time the bytes alone need on the wire. Rows:

* ``direct``: plcstack's AS511 client reading DB5.DW0..63 itself (no gateway), the reference;
* ``gateway, 1 client``: one S5-LAN client reading the same through the gateway;
* ``gateway, 10 clients``: ten S5-LAN clients at once, without and with the read cache (1 s).

    python -m benchmarks.gateway [--wire pty|tcp] [--baud 9600] [--seconds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time

from benchmarks.as511_line_rate import BITS_PER_BYTE, Counter
from plcstack import gateway
from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.sim import as511 as sim_as511
from plcstack.sim.base import Simulator

WORDS = 64
EXPECTED = [0x0500 | k for k in range(WORDS)]


def as511_client(sim: Simulator) -> AS511Client:
    plc = connect(sim.url)
    assert isinstance(plc, AS511Client)
    return plc


def row(label: str, latencies: list[float], seconds: float, wire_bytes: int, baud: int) -> None:
    n = len(latencies)
    limit = wire_bytes / n * BITS_PER_BYTE / baud if n and wire_bytes else 0.0
    lat = sorted(latencies)
    p50 = statistics.median(lat) * 1000
    p99 = lat[min(n - 1, int(n * 0.99))] * 1000
    rate = n / seconds
    text = f"  {label:30s} {rate:7.2f} req/s  p50 {p50:7.1f} ms  p99 {p99:7.1f} ms"
    if wire_bytes:  # the cached rows mostly do not touch the line: no line-rate ratio
        line = 1 / limit
        text += f"  line-rate limit {line:5.2f} req/s  ratio {rate / line:5.3f}"
    print(text)


async def run_clients(url: str, clients: int, seconds: float) -> tuple[list[float], float]:
    """Latencies of the reads of ``clients`` clients for ``seconds``, and the time it took
    until the last answer (requests started near the end finish after ``seconds``)."""
    latencies: list[float] = []
    start = time.perf_counter()
    end = start + seconds

    async def one() -> None:
        # ten clients share one 9600 baud line: a request may wait ~10 x 0.25 s in the queue
        async with connect(url, timeout=10.0) as plc:
            while time.perf_counter() < end:
                t0 = time.perf_counter()
                assert await plc.read("DB5.DW0", WORDS) == EXPECTED
                latencies.append(time.perf_counter() - t0)

    await asyncio.gather(*(one() for _ in range(clients)))
    return latencies, time.perf_counter() - start


async def measure(wire: str, baud: int, seconds: float) -> None:
    start = sim_as511.start_pty if wire == "pty" else sim_as511.start
    head = f"AS511 gateway, {WORDS}-word DB read, {wire} at emulated {baud} baud 8E1"
    print(f"{head}, {seconds:g} s each")
    async with await start(baud=baud) as sim:
        plc = as511_client(sim)
        async with plc:
            counter = Counter(plc)
            await plc.read("DB5.DW0", WORDS)  # system parameters and block address: cached
            counter.take()
            latencies: list[float] = []
            t_start = time.perf_counter()
            while time.perf_counter() < t_start + seconds:
                t0 = time.perf_counter()
                assert await plc.read("DB5.DW0", WORDS) == EXPECTED
                latencies.append(time.perf_counter() - t0)
            elapsed = time.perf_counter() - t_start
            row("direct AS511 client", latencies, elapsed, counter.take(), baud)

        for clients, cache in ((1, None), (10, None), (10, 1.0)):
            plc = as511_client(sim)
            gw = await gateway.start(
                plc,
                s5lan=("127.0.0.1", 0),
                cache_max_age=cache,
                queue_size=32,
                max_wait=10.0,
                # the face guard lets one host hold three quarters of the connections
                s5lan_connections=2 * clients,
            )
            async with gw:
                assert gw.s5lan is not None
                counter = Counter(plc)
                await run_clients(gw.s5lan.url, 1, 0.5)  # warm: addresses cached
                counter.take()
                latencies, elapsed = await run_clients(gw.s5lan.url, clients, seconds)
                label = f"gateway, {clients} client{'s' if clients > 1 else ''}"
                if cache:
                    label += f", cache {cache:g} s"
                wire_bytes = counter.take()
                row(label, latencies, elapsed, 0 if cache else wire_bytes, baud)
                s = gw.stats
                print(f"{'':34s}AS511 reads {s.line_reads}, cache hits {s.cache_hits}")


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--wire", choices=("pty", "tcp"), default="pty")
    parser.add_argument("--baud", type=int, default=9600)
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    asyncio.run(measure(args.wire, args.baud, args.seconds))


if __name__ == "__main__":
    main()
