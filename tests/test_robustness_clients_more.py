"""Promise 2 for the clients that do not fit the generic proxy: the E71 fixed-buffer partner
(a stub E71 in the test), AS511 on a real pty (no connection to close: the line resynchronises),
and FETCH/WRITE with its separate WRITE port (both ports behind misbehaving proxies)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
from collections.abc import Callable
from typing import Any

import pytest

from plcstack.clients import connect
from plcstack.clients.e71_fixed import E71FixedBufferClient
from plcstack.errors import ConnectionLost, PlcError, PlcTimeout, RemoteProtocolError
from plcstack.sim import as511 as as511_sim
from plcstack.sim import fetchwrite as fw_sim
from plcstack.sim.s5memory import Area
from plcstack.url import parse_url
from tests.aio_helpers import ends_quietly
from tests.robust_helpers import MisbehavingProxy, giving_up_soon, record_loop_errors

TIMEOUT = 0.1
ACK = b"\xe0\x00"  # binary fixed-buffer answer "received data taken", end code 00H


class StubE71:
    """A fixed-buffer E71 whose answer to each telegram is scripted by the test."""

    def __init__(self, answer: Callable[[int], bytes | None]) -> None:
        self.answer = answer  # telegram number -> bytes to send back (None: close at once)
        self.telegrams = 0
        self.connections = 0
        self.server: asyncio.Server | None = None
        self.port = 0
        self._writers: list[asyncio.StreamWriter] = []

    async def start(self) -> StubE71:
        self.server = await asyncio.start_server(ends_quietly(self._handle), "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def aclose(self) -> None:
        assert self.server is not None
        self.server.close()
        for w in self._writers:
            w.transport.abort()
        await self.server.wait_closed()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        self._writers.append(writer)
        try:
            while True:
                head = await reader.readexactly(4)  # 60 00 + word count (binary)
                await reader.readexactly(2 * int.from_bytes(head[2:4], "little"))
                self.telegrams += 1
                out = self.answer(self.telegrams)
                if out is None:
                    writer.transport.abort()
                    return
                writer.write(out)
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.transport.abort()


def _fixed(port: int) -> E71FixedBufferClient:
    return E71FixedBufferClient.from_url(parse_url(f"e71+tcp://127.0.0.1:{port}"), timeout=TIMEOUT)


SCRIPTS: dict[str, tuple[Callable[[int], bytes | None], type[PlcError]]] = {
    # the stale second E0 00 must not confirm telegram 2, which the PLC never took
    "twice": (lambda n: ACK + ACK if n == 1 else b"", PlcTimeout),
    "mute": (lambda n: ACK if n == 1 else b"", PlcTimeout),
    "garbage": (lambda n: ACK if n == 1 else b"\x12\x34\x56\x78" * 4, RemoteProtocolError),
    "half_close": (lambda n: ACK if n == 1 else None, ConnectionLost),
}


@pytest.mark.parametrize("script", sorted(SCRIPTS))
async def test_fixed_buffer_send_is_confirmed_only_by_its_own_answer(script: str) -> None:
    answer, expected = SCRIPTS[script]
    async with record_loop_errors() as errors:
        stub = await StubE71(answer).start()
        fb = _fixed(stub.port)
        try:
            async with fb:
                await fb.send([1, 2, 3])
                await asyncio.sleep(0.02)  # the duplicate (if any) arrives now
                with pytest.raises(expected) as info:
                    async with asyncio.timeout(10):
                        await fb.send([4, 5])
                text = str(info.value)
                assert f"127.0.0.1:{stub.port}" in text and "fixed buffer send x2" in text, text
                assert "may or may not have taken the data" in text, text
                await asyncio.sleep(0.05)
                assert stub.telegrams == 2  # sent once, never again
        finally:
            await stub.aclose()
    assert errors.describe() == []


async def test_fixed_buffer_cancelled_send_does_not_block_the_next() -> None:
    """A send given up by the caller: its late E0 00 must not confirm the next telegram, and the
    next send must not be refused as 'still awaiting an answer'."""
    async with record_loop_errors() as errors:
        stub = await StubE71(lambda n: b"" if n == 1 else ACK).start()
        fb = _fixed(stub.port)
        try:
            async with fb:
                with pytest.raises(TimeoutError):
                    await asyncio.wait_for(fb.send([1]), 0.05)
                await fb.send([2])  # answered by its own E0 00
                assert stub.telegrams == 2
        finally:
            await stub.aclose()
    assert errors.describe() == []


async def test_as511_pty_cancelled_read_then_fresh_answers() -> None:
    async with record_loop_errors() as errors:
        sim = await as511_sim.start_pty(char_timeout=0.05)
        try:
            opts: dict[str, Any] = {"char_timeout": 0.05, "nak_backoff": 0.05}
            async with connect(sim.url, timeout=1, **opts) as plc:
                assert await plc.read("MW100") is not None
                sim.machine.mute = True
                with pytest.raises(TimeoutError):
                    await asyncio.wait_for(plc.read("MW100"), 0.05)
                sim.machine.mute = False
                for value in (0x5555, 0x6666):
                    sim.memory.write_area(Area.FLAGS, 100, value.to_bytes(2, "big"))
                    assert await plc.read("MW100") == [value]
        finally:
            await sim.aclose()
    assert errors.describe() == []


# -- AS511 on a real pseudo-terminal ------------------------------------------------------------


async def test_as511_pty_dead_line_then_garbage_then_fresh_answers() -> None:
    async with record_loop_errors() as errors:
        sim = await as511_sim.start_pty(char_timeout=0.05)
        try:
            # the client's own deadlines (a loaded machine may hold a character up for more
            # than 50 ms); short ones only for the requests a dead line never answers
            async with connect(sim.url, nak_backoff=0.05) as plc:
                sim.memory.write_area(Area.FLAGS, 100, b"\x11\x11")
                assert await plc.read("MW100") == [0x1111]
                sim.machine.mute = True  # a dead cable: the client must not hang
                with giving_up_soon(plc, TIMEOUT):
                    with pytest.raises(PlcTimeout) as info:
                        async with asyncio.timeout(10):
                            await plc.read("MW100")
                    assert sim.url in str(info.value) and "read MW100" in str(info.value)
                    with pytest.raises(PlcTimeout, match="write MW100"):
                        await plc.write("MW100", [0x2222])
                    # garbage on the line while the AG is dead: an error, never a value
                    task = asyncio.create_task(plc.read("MW100"))
                    await asyncio.sleep(0.01)
                    os.write(sim._master, b"\x10\x02\x55\xaa\x10\x03" * 5)
                    with pytest.raises((RemoteProtocolError, PlcTimeout)):
                        await asyncio.wait_for(task, 10)
                sim.machine.mute = False
                for value in (0x3333, 0x4444):
                    sim.memory.write_area(Area.FLAGS, 100, value.to_bytes(2, "big"))
                    assert await plc.read("MW100") == [value]
        finally:
            await sim.aclose()
    assert errors.describe() == []


# -- FETCH/WRITE with a separate WRITE port -------------------------------------------------------


@pytest.mark.parametrize("mk", [False, True])
async def test_fetchwrite_write_port_fault_is_typed_and_never_retried(mk: bool) -> None:
    async with record_loop_errors() as errors:
        sim = await fw_sim.start(mk=mk, write_port=0)
        assert sim.write_port is not None
        fetch_proxy = await MisbehavingProxy(sim.host, sim.port).start()
        write_proxy = await MisbehavingProxy(sim.host, sim.write_port).start()
        url = re.sub(r":\d+", f":{fetch_proxy.port}", sim.url, count=1)
        url = url.replace(f"write_port={sim.write_port}", f"write_port={write_proxy.port}")
        try:
            async with connect(url, timeout=TIMEOUT) as plc:
                await plc.write("MW100", [0x1111])
                assert await plc.read("MW100") == [0x1111]
                assert write_proxy.requests == 1 and fetch_proxy.requests == 1
                for fault, expected in (("mute", PlcTimeout), ("close", ConnectionLost)):
                    write_proxy.script.mode = fault
                    sent = write_proxy.requests
                    with pytest.raises(expected, match="may or may not") as info:
                        await plc.write("MW100", [0x2222])
                    assert url in str(info.value) and "write MW100" in str(info.value)
                    await asyncio.sleep(0.05)
                    assert write_proxy.requests == sent + 1  # never resent
                    write_proxy.script.mode = "pass"
                # the FETCH connection was not disturbed, and the next write is its own
                fetch_proxy.script.mode = "twice"  # rejected as misframed, or right
                with contextlib.suppress(RemoteProtocolError):
                    assert await plc.read("MW100") == [0x2222]
                fetch_proxy.script.mode = "pass"
                assert await plc.read("MW100") == [0x2222]  # executed although unconfirmed
                await plc.write("MW100", [0x3333])
                sim.memory.write_area(Area.FLAGS, 102, b"\x44\x44")
                assert await plc.read("MW100", 2) == [0x3333, 0x4444]
        finally:
            await fetch_proxy.aclose()
            await write_proxy.aclose()
            await sim.aclose()
    assert errors.describe() == []
