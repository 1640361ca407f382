"""Native faces on a PLC's one connection: requests/s through a face, the latency a face adds,
and the poll's overruns and p99 with the faces loaded against without.

For each PLC kind the PLC simulator runs as ``plcstack sim`` in a process of its own, and the
network clients in another (both pinned to CPU 1); this process holds the poller and the faces
(pinned to CPU 0), as ``plcstack poll`` would:

* ``s5lan``: an S5-LAN module simulator that takes one connection (the poller's), an S5-LAN
  face, 20 S5-LAN clients;
* ``e71``: an E71 simulator (8 connections), an E71 face (binary, TCP), 12 E71 clients;
* ``as511``: an AS511 simulator (TCP, full speed), a FETCH/WRITE face in the MK header, 8
  FETCH/WRITE clients.

Every client reads 64 words in a closed loop (``DB5.DW0``, ``D0``). Phases, ``--seconds``
each: ``direct`` (one client on the PLC itself, no poller: the reference latency), ``poll``
(the poller alone, 64 words every ``--interval`` s), ``face x1`` (one client through the face
while the poller polls: what the face adds over ``direct``), ``face xN`` (N clients: the
face's requests/s, and the poller's overruns and p99 under that load). The poller's p99 is
its request latency, the wait for the connection included.

    python -m benchmarks.faces [--seconds 5] [--interval 0.01] [--only s5lan|e71|as511]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import sys
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass

from plcstack.clients import connect
from plcstack.gateway.faces import FaceSettings, GatewayFaces
from plcstack.poll.config import parse_poll_config
from plcstack.poll.engine import Poller

WORDS = 64


@dataclass(frozen=True)
class Kind:
    name: str
    sim: list[str]  # plcstack sim ...
    scheme: str  # the PLC's URL scheme
    address: str  # what every client reads
    clients: int
    face: str  # s5lan | e71 | fetchwrite+mk


KINDS = (
    Kind("s5lan", ["s5lan"], "s5lan", "DB5.DW0", 20, "s5lan"),
    Kind("e71", ["e71"], "e71+tcp", "D0", 12, "e71"),
    Kind("as511", ["as511"], "as511+tcp", "DB5.DW0", 8, "fetchwrite+mk"),
)


def pin(cpu: int) -> None:
    if len(os.sched_getaffinity(0)) > 1 and cpu < (os.cpu_count() or 1):
        os.sched_setaffinity(0, {cpu})


def percentiles(values: list[float]) -> tuple[float, float]:
    """p50 and p99 in milliseconds."""
    if not values:
        return float("nan"), float("nan")
    ordered = sorted(values)
    p99 = ordered[min(len(ordered) - 1, int(len(ordered) * 0.99))]
    return statistics.median(ordered) * 1000, p99 * 1000


# -- the clients' process -------------------------------------------------------------------------
async def clients_main(url: str, address: str, clients: int, seconds: float) -> None:
    """``clients`` closed loops on ``url`` for ``seconds``; one JSON line: latencies, time."""
    latencies: list[float] = []
    errors: list[str] = []
    start = time.perf_counter()
    end = start + seconds

    async def one() -> None:
        async with connect(url, timeout=10.0) as plc:
            while time.perf_counter() < end:
                t0 = time.perf_counter()
                try:
                    await plc.read(address, WORDS)
                except Exception as exc:
                    errors.append(str(exc))
                    continue
                latencies.append(time.perf_counter() - t0)

    await asyncio.gather(*(one() for _ in range(clients)))
    elapsed = time.perf_counter() - start
    print(json.dumps({"latencies": latencies, "errors": errors[:3], "seconds": elapsed}))


async def run_clients(url: str, address: str, clients: int, seconds: float) -> dict[str, object]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "benchmarks.faces", "--clients-run", url, address,
        str(clients), str(seconds),
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, _ = await proc.communicate()
    if proc.returncode:
        raise RuntimeError(f"the clients' process failed ({proc.returncode})")
    result: dict[str, object] = json.loads(out)
    return result


# -- the PLC simulator's process ------------------------------------------------------------------
@asynccontextmanager
async def simulator(kind: Kind) -> AsyncIterator[str]:
    """``plcstack sim`` in a child process pinned to CPU 1; yields its URL."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c",
        "import os,sys; from plcstack.cli import main; "
        "os.sched_setaffinity(0, {1}) if len(os.sched_getaffinity(0)) > 1 else None; "
        f"sys.exit(main(['sim', *{kind.sim!r}, '--port', '0', '--idle-timeout', '0']))",
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode()
        host_port = line.split("listening on ")[1].split()[0]
        yield f"{kind.scheme}://{host_port}"
    finally:
        proc.terminate()
        await proc.wait()


@asynccontextmanager
async def face_of(kind: Kind, poller: Poller) -> AsyncIterator[str]:
    """The face of the poller's PLC as a ``[[gateway]]`` entry runs it in ``plcstack poll``
    (64 clients at once); yields the URL its clients use."""
    protocol = "fetchwrite" if kind.face == "fetchwrite+mk" else kind.face
    settings = FaceSettings(
        protocol,  # type: ignore[arg-type]
        "127.0.0.1",
        0,
        "plc",
        mk=kind.face == "fetchwrite+mk",
        max_connections=64,
    )
    async with GatewayFaces([settings], poller.client) as natives:
        (faces,) = natives.plcs
        (server,) = faces.servers
        yield server.url


@dataclass
class PollWindow:
    scans: int
    overruns: int
    latencies: list[float]
    seconds: float


async def poll_window(poller: Poller, seconds: float) -> PollWindow:
    """The poller's counters over the next ``seconds``."""
    stats = poller.stats["plc"]
    scans, overruns, total = stats.scans, stats.overruns, stats.latencies.total
    start = time.perf_counter()
    await asyncio.sleep(seconds)
    elapsed = time.perf_counter() - start
    stats = poller.stats["plc"]
    new = stats.latencies.total - total
    latencies = stats.latencies.tail(new)
    return PollWindow(stats.scans - scans, stats.overruns - overruns, latencies, elapsed)


def report(label: str, latencies: list[float], seconds: float, errors: list[str]) -> str:
    p50, p99 = percentiles(latencies)
    rate = len(latencies) / seconds if seconds else 0.0
    text = f"{label:22s} {rate:9,.0f} req/s  p50 {p50:7.3f} ms  p99 {p99:7.3f} ms"
    return text + (f"  errors {len(errors)}+: {errors[0]}" if errors else "  errors 0")


def poll_report(label: str, window: PollWindow) -> str:
    p50, p99 = percentiles(window.latencies)
    return (
        f"{label:22s} {window.scans / window.seconds:9,.0f} scans/s  p50 {p50:7.3f} ms  "
        f"p99 {p99:7.3f} ms  overruns {window.overruns}"
    )


async def measure(kind: Kind, seconds: float, interval: float) -> None:
    print(f"\n{kind.name}: {kind.clients} clients, {WORDS}-word reads of {kind.address}")
    async with simulator(kind) as url:
        direct = await run_clients(url, kind.address, 1, seconds)
        print(report("direct x1", direct["latencies"], direct["seconds"], direct["errors"]))  # type: ignore[arg-type]
        text = f"""
[poll]
interval = {interval}
timeout = 5.0

[[plc]]
name = "plc"
url = "{url}"

[plc.tags]
words = {{ address = "{kind.address}", count = {WORDS} }}
"""
        async with Poller(parse_poll_config(text)) as poller:
            await asyncio.sleep(1.0)  # connected, the first scans done
            alone = await poll_window(poller, seconds)
            print(poll_report("poll alone", alone))
            async with face_of(kind, poller) as face_url:
                one = await run_clients(face_url, kind.address, 1, seconds)
                print(report("face x1", one["latencies"], one["seconds"], one["errors"]))  # type: ignore[arg-type]
                # the clients' process runs 1 s longer than the poller's window, which starts
                # once its clients are connected and loading (its start-up takes about 0.5 s)
                many_task = asyncio.ensure_future(
                    run_clients(face_url, kind.address, kind.clients, seconds + 1.0)
                )
                await asyncio.sleep(0.8)
                loaded = await poll_window(poller, seconds)
                many = await many_task
                label = f"face x{kind.clients}"
                print(report(label, many["latencies"], many["seconds"], many["errors"]))  # type: ignore[arg-type]
                print(poll_report(f"poll, face x{kind.clients}", loaded))
            d50, d99 = percentiles(direct["latencies"])  # type: ignore[arg-type]
            f50, f99 = percentiles(one["latencies"])  # type: ignore[arg-type]
            print(f"{'added by the face':22s} p50 {f50 - d50:+.3f} ms  p99 {f99 - d99:+.3f} ms")


async def main(args: argparse.Namespace) -> None:
    pin(0)
    print(
        f"native faces, {args.seconds:g} s per phase, poll every {args.interval:g} s; "
        f"this process on CPU 0, simulators and clients on CPU 1"
    )
    for kind in KINDS:
        if not args.only or kind.name in args.only:
            await measure(kind, args.seconds, args.interval)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--interval", type=float, default=0.01)
    parser.add_argument("--only", action="append", choices=[k.name for k in KINDS])
    parser.add_argument("--clients-run", nargs=4, metavar=("URL", "ADDRESS", "N", "SECONDS"))
    parsed = parser.parse_args()
    if parsed.clients_run:
        pin(1)
        url, address, n, secs = parsed.clients_run
        asyncio.run(clients_main(url, address, int(n), float(secs)))
    else:
        asyncio.run(main(parsed))
