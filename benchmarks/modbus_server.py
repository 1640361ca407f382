"""The Modbus TCP server under load: 10 clients reading 100 registers each at 10 Hz, 100 PLCs.

Setup: ``--plcs`` E71 simulators in this process, each with one tag of ``--words`` uint16 values
(D0..) mapped to consecutive holding registers (PLC i at ``hr:i*words``); a ``plcstack serve
modbus`` child process polling them every ``--interval`` seconds and serving them; ``--clients``
libmodbus clients (the C program of the tests, each its own process) each reading ``--count``
registers (client k from ``hr:k*count``, so every client's span covers several PLCs' tags) at
``--hz`` for ``--seconds``.

Measured:

* the response time each client sees for its requests (send to answer, libmodbus's
  ``modbus_read_registers``, monotonic clock): p50, p99, max over all clients' requests;
* the server process's CPU over the window (user + system from /proc, process CPU time, not
  wall clock): poller and Modbus server together, i.e. what ``plcstack serve modbus`` costs,
  and the same window with no client (``--poll-only`` figures come with every run), so the
  difference is what the Modbus side adds;
* failed requests (an exception or a timeout): 0 expected.

The machine is shared: the load average before and after and the CPU count are printed with
the figures; compare runs made at the same time.

    python -m benchmarks.modbus_server [--plcs 100] [--clients 10] [--count 100] [--hz 10]
                                       [--interval 0.1] [--seconds 20]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from plcstack.sim import e71 as sim_e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.modbus_helpers import modbus, modbus_client

ROOT = Path(__file__).resolve().parent.parent


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks  # utime, stime (fields 14, 15)


def write_config(path: Path, urls: list[str], words: int, interval: float) -> None:
    lines = [f"[poll]\ninterval = {interval}\n", '[modbus]\nlisten = "127.0.0.1:0"\n']
    for i, url in enumerate(urls):
        lines.append(f'[[plc]]\nname = "plc{i}"\nurl = "{url}"\n[plc.tags]')
        lines.append(
            f'w = {{ address = "D0", type = "uint16", count = {words}, modbus = "hr:{i * words}" }}'
        )
        lines.append("")
    path.write_text("\n".join(lines))


async def _serve(config: Path) -> tuple[asyncio.subprocess.Process, str]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        "serve",
        "modbus",
        str(config),
        stderr=asyncio.subprocess.PIPE,
        cwd=ROOT,
    )
    assert proc.stderr is not None
    async with asyncio.timeout(30):
        while True:
            line = (await proc.stderr.readline()).decode()
            if not line:
                raise RuntimeError(f"plcstack serve modbus ended: exit {await proc.wait()}")
            if "listening on " in line:
                endpoint = line.split("listening on ", 1)[1].split()[0]
                break
    asyncio.create_task(_drain(proc.stderr))  # noqa: RUF006 - ends with the process
    return proc, endpoint


async def _drain(stream: asyncio.StreamReader) -> None:
    while await stream.readline():
        pass


async def _client(
    endpoint: str, seconds: float, hz: float, start: int, count: int
) -> tuple[list[int], int]:
    host, port = endpoint.rsplit(":", 1)
    proc = await asyncio.create_subprocess_exec(
        str(modbus_client()),
        host,
        port,
        "1",
        "bench",
        str(seconds),
        str(hz),
        str(start),
        str(count),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"client failed: {err.decode()}")
    lines = out.decode().split()
    failures = int(lines[lines.index("failures") + 1])
    return [int(x) for x in lines[: lines.index("failures")]], failures


async def main(args: argparse.Namespace) -> None:
    memories = [MelsecMemory() for _ in range(args.plcs)]
    for i, memory in enumerate(memories):
        memory.write_words("D", 0, [(i * args.words + j) & 0xFFFF for j in range(args.words)])
    sims = [await sim_e71.start(memory) for memory in memories]
    tmp = Path(tempfile.mkdtemp(prefix="modbus-bench-"))
    config = tmp / "bench.toml"
    write_config(config, [s.url for s in sims], args.words, args.interval)
    proc, endpoint = await _serve(config)
    try:
        # every PLC polled: each client's span answers
        async with asyncio.timeout(30):
            while True:
                spans = [("rh", k * args.count, args.count) for k in range(args.clients)]
                answers = await modbus(endpoint, *(x for span in spans for x in span))
                if all(a.startswith("ok ") for a in answers):
                    break
                await asyncio.sleep(0.2)
        first = answers[0].split()[1:]
        assert [int(w) for w in first] == list(range(args.count)), "wrong registers served"
        load_before = os.getloadavg()
        # the same window with no client: what polling alone costs
        idle0, t0 = cpu_seconds(proc.pid), time.monotonic()
        await asyncio.sleep(args.seconds)
        idle_cpu, idle_wall = cpu_seconds(proc.pid) - idle0, time.monotonic() - t0
        busy0, t1 = cpu_seconds(proc.pid), time.monotonic()
        results = await asyncio.gather(
            *(
                _client(endpoint, args.seconds, args.hz, k * args.count, args.count)
                for k in range(args.clients)
            )
        )
        busy_cpu, busy_wall = cpu_seconds(proc.pid) - busy0, time.monotonic() - t1
        load_after = os.getloadavg()
    finally:
        proc.terminate()
        await proc.wait()
        for sim in sims:
            await sim.aclose()
    latencies = sorted(x for lat, _ in results for x in lat)
    failures = sum(f for _, f in results)
    p99 = latencies[min(len(latencies) - 1, int(len(latencies) * 0.99))]
    requests = len(latencies) + failures
    print(
        f"setup: {args.plcs} PLCs (E71 simulators, one {args.words}-word tag each, poll interval"
        f" {args.interval} s), {args.clients} libmodbus clients x {args.count} registers at"
        f" {args.hz} Hz for {args.seconds} s; {os.cpu_count()} CPUs, load average"
        f" {load_before[0]:.2f} before, {load_after[0]:.2f} after"
    )
    print(
        f"requests: {requests} ({requests / busy_wall:.0f}/s), failed {failures}; response time"
        f" p50 {statistics.median(latencies) / 1000:.2f} ms, p99 {p99 / 1000:.2f} ms,"
        f" max {latencies[-1] / 1000:.2f} ms"
    )
    print(
        f"server process CPU: {busy_cpu:.2f} s in {busy_wall:.1f} s with clients"
        f" ({100 * busy_cpu / busy_wall:.1f} % of one core); {idle_cpu:.2f} s in {idle_wall:.1f} s"
        f" polling only ({100 * idle_cpu / idle_wall:.1f} %); Modbus side"
        f" {1e6 * (busy_cpu / busy_wall - idle_cpu / idle_wall) * busy_wall / max(requests, 1):.0f}"
        " us CPU per request"
    )


def cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--plcs", type=int, default=100)
    parser.add_argument("--words", type=int, default=10, help="registers per PLC")
    parser.add_argument("--clients", type=int, default=10)
    parser.add_argument("--count", type=int, default=100, help="registers per request")
    parser.add_argument("--hz", type=float, default=10.0)
    parser.add_argument("--interval", type=float, default=0.1, help="poll interval (s)")
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    if args.clients * args.count > args.plcs * args.words:
        parser.error("the clients' spans need clients x count <= plcs x words registers")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main(args))


if __name__ == "__main__":
    cli()
