"""Promise 1: no simulator crashes or stops serving, whatever bytes arrive.

Every simulator gets, over real loopback sockets (and a real pty for AS511): random bytes,
every kind of bad variant of a real request frame (truncations = disconnect mid-frame, 2-byte
fields forced to FFFF/0000 = oversized or zero counts, bit flips), RST and FIN disconnects. Then a
fresh client must get correct answers from it, and asyncio must have reported nothing unhandled.
Every loop is bounded in count and every wait in time.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import socket
import struct
import zlib
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from plcstack.clients import connect
from plcstack.clients.base import Client
from plcstack.clients.e71_fixed import E71FixedBufferClient
from plcstack.sim import as511 as as511_sim
from plcstack.sim import e71 as e71_sim
from plcstack.sim import fetchwrite as fw_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.sim.e71_fixed import FixedBufferSimulator, start_fixed_buffer
from plcstack.url import parse_url
from tests.aio_helpers import eventually
from tests.robust_helpers import capture_request, mutations, record_loop_errors

# PLCSTACK_FUZZ_SCALE=10 for a longer exploratory run (the default keeps the file fast)
SCALE = int(os.environ.get("PLCSTACK_FUZZ_SCALE", "1"))
RANDOM_CONNECTIONS = 20 * SCALE
MUTATIONS = 60 * SCALE
BATCH = 8


async def _tcp_poke(host: str, port: int, payload: bytes, how: str) -> None:
    """One connection: send ``payload``, maybe glance at an answer, then leave as ``how`` says."""
    try:
        async with asyncio.timeout(1.0):
            reader, writer = await asyncio.open_connection(host, port)
    except (OSError, TimeoutError):
        return  # refused while the simulator was full: fine, it must still serve later
    try:
        writer.write(payload)
        if how == "rst":
            sock = writer.get_extra_info("socket")
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            writer.transport.abort()
        else:
            if how == "glance":
                with contextlib.suppress(TimeoutError, OSError):
                    async with asyncio.timeout(0.02):
                        await reader.read(4096)
            writer.close()
    except OSError:
        writer.transport.abort()
    # retrieve the close outcome (a reset) so only the simulator's own leftovers get reported
    with contextlib.suppress(OSError):
        await writer.wait_closed()


async def _tcp_fuzz(host: str, port: int, frames: list[bytes], seed: int) -> None:
    rng = random.Random(f"{seed}-{SCALE}")
    payloads: list[bytes] = [
        rng.randbytes(rng.randrange(1, 300)) for _ in range(RANDOM_CONNECTIONS)
    ]
    for frame in frames:
        payloads += mutations(frame, rng, MUTATIONS // max(len(frames), 1))
    hows = ("rst", "fin", "glance")
    for i in range(0, len(payloads), BATCH):
        batch = payloads[i : i + BATCH]
        await asyncio.gather(*(_tcp_poke(host, port, p, rng.choice(hows)) for p in batch))


async def _udp_fuzz(host: str, port: int, frames: list[bytes], seed: int) -> None:
    rng = random.Random(f"{seed}-{SCALE}")
    payloads = [rng.randbytes(rng.randrange(1, 300)) for _ in range(RANDOM_CONNECTIONS)]
    for frame in frames:
        payloads += mutations(frame, rng, MUTATIONS // max(len(frames), 1))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for p in payloads:
            sock.sendto(p, (host, port))
        await asyncio.sleep(0.05)


async def _roundtrip(url: str, address: str, seed: int, **opts: Any) -> list[bytes]:
    """A fresh client writes a new value and reads it back; returns captured request frames."""
    value = random.Random(seed).randrange(1, 0xFF)
    async with connect(url, timeout=2, **opts) as plc:
        w = await capture_request(plc, lambda: plc.write(address, [value]))
        r = await capture_request(plc, lambda: _check(plc, address, value))
    return [w, r]


async def _check(plc: Client, address: str, value: int) -> None:
    assert await plc.read(address, 1) == [value]


SimStarter = Callable[[], Awaitable[Any]]

TCP_CASES: dict[str, tuple[SimStarter, str]] = {
    "e71-tcp-binary": (lambda: e71_sim.start(), "D100"),
    "e71-tcp-ascii": (lambda: e71_sim.start(code="ascii"), "D100"),
    "s5lan": (lambda: s5lan_sim.start(), "MW100"),
    "as511-tcp": (lambda: as511_sim.start(), "MB10"),
    "fetchwrite-raw": (lambda: fw_sim.start(), "MW100"),
    "fetchwrite-mk": (lambda: fw_sim.start(mk=True), "MW100"),
}


@pytest.mark.parametrize("name", sorted(TCP_CASES))
async def test_tcp_simulator_survives_garbage(name: str) -> None:
    starter, address = TCP_CASES[name]
    async with record_loop_errors() as errors:
        sim = await starter()
        try:
            frames = await _roundtrip(sim.url, address, 1)
            await _tcp_fuzz(sim.host, sim.port, frames, seed=zlib.crc32(name.encode()))
            if name == "s5lan":  # one connection only (D.A4): the fuzz ones must be released
                await eventually(lambda: sim.active_connections == 0, "fuzz connections gone")
            elif name.startswith("e71"):
                await eventually(lambda: not sim.connections, "fuzz connections gone")
            await _roundtrip(sim.url, address, 2)
            await _roundtrip(sim.url, address, 3)
        finally:
            await sim.aclose()
    assert errors.describe() == []


@pytest.mark.parametrize("mk", [False, True])
async def test_fetchwrite_with_write_port_survives_garbage(mk: bool) -> None:
    async with record_loop_errors() as errors:
        sim = await fw_sim.start(mk=mk, write_port=0)
        try:
            frames = await _roundtrip(sim.url, "MW100", 1)
            assert sim.write_port is not None
            await _tcp_fuzz(sim.host, sim.port, frames, seed=11)
            await _tcp_fuzz(sim.host, sim.write_port, frames, seed=12)
            await _roundtrip(sim.url, "MW100", 2)
        finally:
            await sim.aclose()
    assert errors.describe() == []


@pytest.mark.parametrize("code", ["binary", "ascii"])
async def test_e71_udp_simulator_survives_garbage(code: str) -> None:
    async with record_loop_errors() as errors:
        sim = await e71_sim.start(transport="udp", code=code)  # type: ignore[arg-type]
        try:
            frames = await _roundtrip(sim.url, "D100", 1)
            await _udp_fuzz(sim.host, sim.port, frames, seed=5)
            await _roundtrip(sim.url, "D100", 2)
        finally:
            await sim.aclose()
    assert errors.describe() == []


async def _fixed_check(sim: FixedBufferSimulator, words: tuple[int, ...]) -> bytes:
    """A fresh partner sends ``words`` and gets E0 00 once the PLC took them; then the PLC
    sends back. Returns the partner's request frame."""
    while sim.pending():  # the PLC program takes whatever the fuzz managed to store
        await sim.receive(timeout=1)
    fb = E71FixedBufferClient.from_url(parse_url(sim.url), timeout=2)
    async with fb:
        if sim.procedure:
            send = asyncio.create_task(capture_request(fb, lambda: fb.send(words)))
            assert await sim.receive(timeout=2) == words
            frame = await asyncio.wait_for(send, 2)
            plc_send = asyncio.create_task(sim.send([0x1234]))
            assert await fb.receive(timeout=2) == (0x1234,)  # taken -> E0 00 to the PLC
            assert await asyncio.wait_for(plc_send, 2) == 0
        else:
            data = bytes(words)
            frame = await capture_request(fb, lambda: fb.send_raw(data))
            assert await sim.receive(timeout=2) == data
    return frame


FIXED_CASES = [("tcp", "binary", True), ("tcp", "ascii", True), ("udp", "binary", True)]
FIXED_CASES += [("tcp", "binary", False)]


@pytest.mark.parametrize(("transport", "code", "procedure"), FIXED_CASES)
async def test_e71_fixed_buffer_simulator_survives_garbage(
    transport: str, code: str, procedure: bool
) -> None:
    async with record_loop_errors() as errors:
        sim = await start_fixed_buffer(
            transport=transport,  # type: ignore[arg-type]
            code=code,  # type: ignore[arg-type]
            procedure=procedure,
            ack_timeout=1,
        )
        try:
            frame = await _fixed_check(sim, (1, 2, 3))
            if transport == "udp":
                await _udp_fuzz(sim.host, sim.port, [frame], seed=21)
            else:
                await _tcp_fuzz(sim.host, sim.port, [frame], seed=22)
                await eventually(lambda: sim._tcp is None, "fuzz connection gone")
            await _fixed_check(sim, (4, 5, 6))
        finally:
            await sim.aclose()
    assert errors.describe() == []


async def test_as511_pty_simulator_survives_garbage() -> None:
    async with record_loop_errors() as errors:
        sim = await as511_sim.start_pty()
        try:
            frames = await _roundtrip(sim.url, "MB10", 1)
            rng = random.Random(31 * SCALE)
            payloads = [rng.randbytes(rng.randrange(1, 200)) for _ in range(10)]
            for frame in frames:
                payloads += mutations(frame, rng, 15)
            await eventually(lambda: sim.idle, "line idle")  # the last DLE ACK is in
            sent = sim.received
            for p in payloads:  # a PG that talks nonsense, then lets go of the port mid-frame
                fd = os.open(sim.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
                try:
                    sent += os.write(fd, p)
                    await asyncio.sleep(0.002)
                finally:
                    os.close(fd)
            # every byte through the pty (the kernel passes them on in its own time), handled,
            # and the AG back from its character timeout
            await eventually(lambda: sim.received == sent and sim.idle, "garbage taken, line idle")
            await _roundtrip(sim.url, "MB10", 2)
            await _roundtrip(sim.url, "MB10", 3)
        finally:
            await sim.aclose()
    assert errors.describe() == []
