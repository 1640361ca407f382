"""The AS511 gateway's S5-LAN and FETCH/WRITE servers against clients that trickle a request
one byte at a time to hold one of the few connections (slowloris), over real loopback sockets,
in front of the AS511 simulator."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import pytest

from plcstack import gateway
from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.sim import as511 as sim_as511
from plcstack.sim import fetchwrite as fw_sim

#: 26 bytes of an S5-LAN header and 16 of a FETCH/WRITE FETCH header
S5LAN_HEADER = b"S5\x10\x01" + bytes(22)
FETCH_HEADER = bytes.fromhex("5335100103050308010a00050014ff02")


@asynccontextmanager
async def running() -> AsyncIterator[gateway.Gateway]:
    async with await sim_as511.start() as sim:
        plc = connect(sim.url)
        assert isinstance(plc, AS511Client)
        gw = await gateway.start(plc, s5lan=("127.0.0.1", 0), fetchwrite=("127.0.0.1", 0))
        async with gw:
            yield gw


async def _trickled_until_closed(port: int, header: bytes, every: float) -> bool:
    """Send ``header`` minus its last byte, one byte every ``every`` seconds; whether the
    server ended the connection before all of it was sent (5 s bound)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)

    async def trickle() -> None:
        for byte in header[:-1]:
            writer.write(bytes([byte]))
            await asyncio.sleep(every)

    dripping = asyncio.create_task(trickle())
    try:
        async with asyncio.timeout(5):
            while await reader.read(65536):
                pass
        return not dripping.done()
    except ConnectionError:
        return not dripping.done()
    except TimeoutError:
        return False
    finally:
        dripping.cancel()
        await asyncio.gather(dripping, return_exceptions=True)
        writer.transport.abort()


async def test_s5lan_header_trickled_byte_by_byte_is_ended() -> None:
    """Before: the 1 s data timeout restarted with every byte, so a header sent one byte every
    0.4 s held one of the gateway's 8 S5-LAN connections for ever. After: the request must be
    complete 1 s after its first byte."""
    async with running() as gw:
        assert gw.s5lan is not None
        assert await _trickled_until_closed(gw.s5lan.port, S5LAN_HEADER, 0.4)
        assert gw.s5lan.late_frames == 1
        async with connect(gw.s5lan.url + "?timeout=3") as plc:
            assert await plc.read("MB0") == [0]


async def test_fetchwrite_header_trickled_byte_by_byte_is_ended(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before: the idle timeout (600 s) restarted with every byte, so a FETCH header sent one
    byte a minute held a FETCH/WRITE connection (of 16) for ever. After: a job must be complete
    FRAME_TIMEOUT seconds after its first byte (shortened here)."""
    monkeypatch.setattr(fw_sim, "FRAME_TIMEOUT", 0.5, raising=False)
    async with running() as gw:
        assert gw.fetchwrite is not None
        assert await _trickled_until_closed(gw.fetchwrite.port, FETCH_HEADER, 0.4)
        assert gw.fetchwrite.late_frames == 1
        async with connect(gw.fetchwrite.url + "?timeout=3") as plc:
            assert await plc.read("MB0") == [0]
