"""What one client's garbage costs in the log: a Modbus client sending malformed frames for a
bounded time to ``plcstack serve modbus`` at its default log level (what an operator's journal
gets), counted in lines and bytes of the server's stderr.

The client mixes what a fuzzer or a broken panel sends: frames whose MBAP header is broken
(protocol id not 0, length out of range: the server closes the connection, the client connects
again), writes whose byte count does not match their data (answered ILLEGAL DATA VALUE), and
unknown function codes (answered ILLEGAL FUNCTION). One connection at a time, as fast as the
server answers, seeded, for ``--seconds`` or ``--frames``, whichever comes first.

    python -m benchmarks.garbage_log [--seconds 30] [--frames 6000]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import random
import struct
import sys
import tempfile
import time
from pathlib import Path

import plcstack
from plcstack.sim import e71 as sim_e71

#: the server runs the plcstack this process imported (a checkout to compare, or the install)
SOURCE = Path(plcstack.__file__).resolve().parent.parent

CONFIG = """[poll]
interval = 0.5
[modbus]
endpoint = "127.0.0.1:0"
[[plc]]
name = "p"
url = "{url}"
[plc.tags]
w = {{ address = "D0", type = "uint16", count = 10, modbus = "hr:0" }}
"""


def garbage(rng: random.Random, transaction: int) -> tuple[bytes, bool]:
    """One malformed frame and whether the server closes the connection for it."""
    kind = rng.randrange(3)
    if kind == 0:  # broken framing: protocol id or length
        if rng.random() < 0.5:
            return struct.pack(">HHHB", transaction, rng.randrange(1, 0xFFFF), 6, 1) + bytes(
                5
            ), True
        return struct.pack(">HHHB", transaction, 0, rng.choice((0, 1, 255, 4000)), 1), True
    if kind == 1:  # write multiple registers whose byte count does not match
        count = rng.randrange(1, 10)
        data = bytes(rng.randrange(256) for _ in range(2 * count + 1))
        pdu = struct.pack(">BHHB", 16, 0, count, 2 * count + 2) + data
    else:  # a function code Modbus does not have
        pdu = bytes([rng.choice((0, 9, 0x2A, 0x55, 0x7F))]) + bytes(4)
    return struct.pack(">HHHB", transaction, 0, len(pdu) + 1, 1) + pdu, False


async def flood(endpoint: str, seconds: float, frames: int) -> tuple[int, int]:
    """Frames sent and connections opened."""
    host, port = endpoint.rsplit(":", 1)
    rng = random.Random(7)
    sent = connections = 0
    end = time.monotonic() + seconds
    while sent < frames and time.monotonic() < end:
        reader, writer = await asyncio.open_connection(host, int(port))
        connections += 1
        try:
            while sent < frames and time.monotonic() < end:
                frame, closes = garbage(rng, sent & 0xFFFF)
                writer.write(frame)
                sent += 1
                if closes:
                    await reader.read()  # until the server closed
                    break
                await reader.read(260)  # the exception answer
        except ConnectionError:
            pass
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()
    return sent, connections


async def main(args: argparse.Namespace) -> None:
    sim = await sim_e71.start()
    tmp = Path(tempfile.mkdtemp(prefix="garbage-log-"))
    config = tmp / "plant.toml"
    config.write_text(CONFIG.format(url=sim.url))
    env = dict(os.environ, PYTHONPATH=str(SOURCE))
    proc = await asyncio.create_subprocess_exec(
        *(sys.executable, "-m", "plcstack", "serve", "modbus", str(config)),
        stderr=asyncio.subprocess.PIPE,
        env=env,
    )
    assert proc.stderr is not None
    lines: list[bytes] = []
    try:
        async with asyncio.timeout(30):
            while True:
                line = await proc.stderr.readline()
                if not line:
                    raise RuntimeError(f"plcstack serve modbus ended: exit {await proc.wait()}")
                if b"listening on " in line:
                    endpoint = line.decode().split("listening on ", 1)[1].split()[0]
                    break

        async def collect() -> None:
            assert proc.stderr is not None
            while line := await proc.stderr.readline():
                lines.append(line)

        collector = asyncio.create_task(collect())
        start = time.monotonic()
        sent, connections = await flood(endpoint, args.seconds, args.frames)
        took = time.monotonic() - start
        proc.terminate()
        await proc.wait()
        await collector
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        await sim.aclose()
    print(
        f"{sent} malformed frames on {connections} connections in {took:.1f} s: the server's"
        f" stderr (default log level) got {len(lines)} lines, {sum(map(len, lines))} bytes"
    )
    for line in lines[: args.show]:
        print("  " + line.decode(errors="replace").rstrip())


def cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--frames", type=int, default=6000)
    parser.add_argument("--show", type=int, default=6, help="log lines to print")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main(parser.parse_args()))


if __name__ == "__main__":
    cli()
