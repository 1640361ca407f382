"""Shared client policy: single flight, close on deadline, no stale replies, backoff, no retries.

Uses a toy line protocol ("ASK n" -> "n") so the policy is tested apart from any PLC codec.
"""

import asyncio
from collections.abc import Sequence
from typing import Any

import pytest

from plcstack.clients.exchange import ClientCodec, RequestClient
from plcstack.clients.flight import ConnectTurns
from plcstack.codecs._common import NEED_DATA, NeedData, ReceiveBuffer
from plcstack.errors import ConnectFailed, ConnectionLost, PlcTimeout, RemoteProtocolError
from plcstack.transports import Backoff, TcpTransport
from plcstack.url import PlcUrl
from tests.aio_helpers import ends_quietly


class LineCodec:
    def __init__(self) -> None:
        self.buf = ReceiveBuffer()

    def send(self, request: bytes) -> bytes:
        return request + b"\n"

    def receive_data(self, data: bytes) -> None:
        self.buf.feed(data)

    def next_event(self) -> bytes | NeedData:
        data = self.buf.peek()
        if b"\n" not in data:
            return NEED_DATA
        line = self.buf.take(data.index(b"\n") + 1)[:-1]
        if line.startswith(b"!"):
            raise RemoteProtocolError(f"garbage {line!r}")
        return line


class LineClient(RequestClient[bytes]):
    @classmethod
    def from_url(cls, url: PlcUrl, **options: Any) -> "LineClient":  # pragma: no cover
        raise NotImplementedError

    def new_codec(self) -> ClientCodec:
        return LineCodec()

    async def read(self, address: str, count: int = 1) -> list[int]:
        reply = await self.exchange(address.encode(), f"read {address}", is_write=False)
        return [int(reply)]

    async def write(self, address: str, values: Sequence[int] | Sequence[bool]) -> None:
        await self.exchange(address.encode(), f"write {address}", is_write=True)


class LineServer:
    """Answers "ASK n" with "n" after ``delay`` seconds; "DIE" closes; "BAD" sends garbage."""

    def __init__(self) -> None:
        self.delay = 0.0
        self.connections = 0

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        try:
            while line := await reader.readline():
                cmd = line.strip()
                if cmd == b"DIE":
                    break
                if cmd == b"BAD":
                    writer.write(b"!!!\n")
                    continue
                await asyncio.sleep(self.delay)
                writer.write(cmd.split()[-1] + b"\n")
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            writer.close()


@pytest.fixture
async def line_server() -> Any:
    srv = LineServer()
    server = await asyncio.start_server(ends_quietly(srv.handle), "127.0.0.1", 0)
    srv.port = server.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
    srv.server = server  # type: ignore[attr-defined]
    yield srv
    server.close()


def make_client(port: int, **kw: Any) -> LineClient:
    return LineClient(f"line://127.0.0.1:{port}", TcpTransport("127.0.0.1", port), **kw)


async def test_requests_are_single_flight_and_replies_match(line_server: Any) -> None:
    async with make_client(line_server.port) as plc:
        results = await asyncio.gather(*(plc.read(f"ASK {i}") for i in range(50)))
    assert results == [[i] for i in range(50)]
    assert plc.stats.requests == 50 and plc.stats.errors == 0


async def test_timeout_closes_so_a_late_reply_is_never_the_next_answer(line_server: Any) -> None:
    async with make_client(line_server.port, timeout=0.1) as plc:
        line_server.delay = 0.3
        with pytest.raises(PlcTimeout) as info:
            await plc.read("ASK 1")
        assert "line://127.0.0.1" in str(info.value) and "read ASK 1" in str(info.value)
        assert not plc.transport.is_open
        line_server.delay = 0.0
        await asyncio.sleep(0.4)  # the late "1" would have arrived by now on the old connection
        assert await plc.read("ASK 2") == [2]
    assert line_server.connections == 2
    assert plc.stats.timeouts == 1


async def test_write_timeout_says_outcome_unknown_and_is_not_retried(line_server: Any) -> None:
    async with make_client(line_server.port, timeout=0.1) as plc:
        line_server.delay = 0.3
        with pytest.raises(PlcTimeout, match="may or may not have been executed"):
            await plc.write("ASK 1", [1])
    assert plc.stats.requests == 1


async def test_peer_closing_mid_request_is_connection_lost(line_server: Any) -> None:
    async with make_client(line_server.port) as plc:
        with pytest.raises(ConnectionLost, match="lost"):
            await plc.read("DIE")
        assert await plc.read("ASK 3") == [3]  # reconnects by itself


async def test_malformed_reply_closes_the_connection(line_server: Any) -> None:
    async with make_client(line_server.port) as plc:
        with pytest.raises(RemoteProtocolError) as info:
            await plc.read("BAD")
        assert str(info.value).startswith("line://127.0.0.1")
        assert not plc.transport.is_open
        assert await plc.read("ASK 4") == [4]


async def test_dead_plc_backs_off_and_comes_back(line_server: Any) -> None:
    port = line_server.port
    plc = make_client(port, backoff=Backoff(initial=0.2, maximum=0.2, jitter=0.0))
    await plc.open()
    line_server.server.close()
    await line_server.server.wait_closed()
    with pytest.raises(ConnectionLost):
        await plc.read("DIE")  # server side closes; the listener is gone now
    with pytest.raises(ConnectFailed, match="cannot connect"):
        await plc.read("ASK 5")
    with pytest.raises(ConnectFailed, match="next reconnect attempt in 0\\.[12] s"):
        await plc.read("ASK 5")  # fails fast inside the backoff window, no connect attempt
    assert plc.stats.connect_failures == 1
    server = await asyncio.start_server(ends_quietly(line_server.handle), "127.0.0.1", port)
    await asyncio.sleep(0.25)
    assert await plc.read("ASK 6") == [6]
    await plc.aclose()
    server.close()
    with pytest.raises(ConnectionLost, match="client is closed"):
        await plc.read("ASK 7")


async def test_a_connect_waits_for_its_turn_before_its_timeout_starts(line_server: Any) -> None:
    """Clients of one poller share connect turns; waiting for one is not connecting, so a
    fleet starting thousands of connects does not time them out on its own backlog."""
    turns = ConnectTurns(1, hold=60.0)
    plc = make_client(line_server.port, connect_timeout=0.2)
    plc.connect_turns = turns
    async with turns.turn():  # another connect holds the one turn, longer than the timeout
        opening = asyncio.create_task(plc.open())
        await asyncio.sleep(0.5)
        assert not opening.done()
    await opening
    async with plc:
        assert await plc.read("ASK 7") == [7]
    assert plc.stats.connect_failures == 0
