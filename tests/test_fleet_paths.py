"""Issue 16's fast paths decide exactly as the general paths they shortcut.

* E71: a word read already checked reuses its request object and bytes; a normal 01H answer
  over TCP is cut and decoded in one step. Against the general path on random answer streams.
* The check for unsolicited bytes before a request: the general path lets the event loop run
  once; the fast path asks the kernel (one poll) and skips that pass when nothing waits. Both must
  find stale bytes wherever they are (already delivered, or still in the kernel), over TCP and
  UDP, and never return a stale answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack import connect
from plcstack.clients.e71 import E71Client
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import (
    Code,
    E71ClientConnection,
    ReadBits,
    ReadWords,
    encode_request,
    parse_address,
)
from plcstack.errors import AddressError, PlcError, PlcTimeout
from plcstack.poll.samples import flatten
from plcstack.sim import e71 as sim_e71
from plcstack.transports.tcp import TcpTransport
from plcstack.transports.udp import UdpTransport
from tests.aio_helpers import blocked_until, ends_quietly, eventually
from tests.test_client_base import LineClient
from tests.test_codec_fast_paths import _decode_all


class _StaleServer:
    """Answers "ASK n" with "n"; ``extra`` bytes follow the answer to ``extra_after`` (a
    duplicated or confused answer), ``delay`` seconds later. Runs in threads, not on the test's
    event loop, so that it sends while the loop is blocked (bytes reach the kernel, not us)."""

    def __init__(self) -> None:
        self.connections = 0
        self.extra = b""
        self.extra_after = b""
        self.close_after = b""
        self.delay = 0.0
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                conn, _ = self.listener.accept()
                self.connections += 1
                threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError), conn.makefile("rb") as lines:
            for line in lines:
                answer = line.split()[-1]
                conn.sendall(answer + b"\n")
                if answer == self.close_after:
                    return
                if self.extra and answer == self.extra_after:
                    time.sleep(self.delay)
                    conn.sendall(self.extra)

    def transport(self) -> TcpTransport:
        return TcpTransport("127.0.0.1", self.port)

    def close(self) -> None:
        self.listener.close()


class _StaleUdpServer:
    """Answers datagram "ASK n" with "n"; after answering ``extra_after`` it sends ``extra`` too
    (a duplicated answer), ``delay`` seconds later. A thread, so it sends while the test's loop
    is blocked (the datagram waits in the kernel)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.sources: set[tuple[str, int]] = set()
        self.extra = b""
        self.extra_after = b""
        self.delay = 0.0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                data, source = self.sock.recvfrom(100)
                self.sources.add(source)
                answer = data.split()[-1]
                self.sock.sendto(answer + b"\n", source)
                if self.extra and answer == self.extra_after:
                    time.sleep(self.delay)
                    self.sock.sendto(self.extra, source)

    @property
    def connections(self) -> int:
        """Distinct local ports seen: each reconnect of the client opens a fresh socket."""
        return len(self.sources)

    def transport(self) -> UdpTransport:
        return UdpTransport("127.0.0.1", self.port)

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def stale_server() -> Any:
    srv = _StaleServer()
    yield srv
    srv.close()


@pytest.fixture(params=["tcp", "udp"])
def stale_peer(request: pytest.FixtureRequest) -> Any:
    """The stale-answer peer over TCP (a stream) or UDP (datagrams): the same checks hold."""
    srv = _StaleServer() if request.param == "tcp" else _StaleUdpServer()
    yield srv
    srv.close()


async def test_quiet_and_input_waiting_see_what_the_loop_has_not_read(stale_peer: Any) -> None:
    transport = stale_peer.transport()
    await transport.open(1.0)
    try:
        transport.write(b"ASK 1\n")
        assert await transport.read() == b"1\n"
        # nothing in the kernel, nothing delivered
        assert transport.quiet() and not transport.input_waiting()
        transport.write(b"ASK 2\n")
        # the loop does not run: the answer waits in the kernel
        blocked_until(transport.input_waiting, "the answer is in the kernel")
        assert not transport.quiet() and transport.input_waiting()
        assert transport.take_received() == []
        # the loop reads it now: queued, so still not quiet
        await eventually(lambda: not transport.input_waiting(), "the loop read the answer")
        assert not transport.quiet() and not transport.input_waiting()
        assert transport.take_received() == [b"2\n"]
        assert transport.quiet()
    finally:
        transport.abort()
    # closed: "cannot tell", the general path
    assert not transport.quiet() and transport.input_waiting()


@pytest.mark.parametrize("where", ["delivered", "in-kernel"])
async def test_stale_bytes_are_found(stale_peer: Any, where: str) -> None:
    client = LineClient(f"line://127.0.0.1:{stale_peer.port}", stale_peer.transport())
    async with client:
        assert await client.read("ASK 1") == [1]
        stale_peer.extra = b"77\n"  # a second answer to "ASK 2", 20 ms late
        stale_peer.extra_after = b"2"
        stale_peer.delay = 0.02
        assert await client.read("ASK 2") == [2]
        transport = client.transport
        if where == "delivered":  # the loop has read the stale answer into the protocol
            await eventually(
                lambda: not transport.quiet() and not transport.input_waiting(),
                "the stale answer is delivered",
            )
        else:  # the stale answer waits in the kernel
            blocked_until(transport.input_waiting, "the stale answer is in the kernel")
        # never 77: the stale answer is found, the connection (UDP: the socket, a new local
        # port) replaced, the request sent anew
        assert await client.read("ASK 3") == [3]
        assert client.stats.errors == 1
        assert stale_peer.connections == 2
        assert await client.read("ASK 4") == [4]
        assert stale_peer.connections == 2


@pytest.mark.parametrize("where", ["delivered", "in-kernel"])
async def test_peer_close_between_requests_reconnects(stale_server: Any, where: str) -> None:
    """The PLC closed the connection after an answer: the next request reconnects at once, as
    it must when the end of stream waits in the kernel (the fast path's poll reports it)."""
    client = LineClient(
        f"line://127.0.0.1:{stale_server.port}", TcpTransport("127.0.0.1", stale_server.port)
    )
    stale_server.close_after = b"5"
    async with client:
        assert await client.read("ASK 5") == [5]
        if where == "delivered":
            await eventually(lambda: not client.transport.is_open, "the end of stream is seen")
        else:  # the end of stream waits in the kernel
            blocked_until(client.transport.input_waiting, "the end of stream is in the kernel")
            assert client.transport.is_open
        assert await client.read("ASK 6") == [6]
        assert stale_server.connections == 2
        assert client.stats.errors == 0


async def test_clean_requests_need_one_connection(stale_server: Any) -> None:
    client = LineClient(
        f"line://127.0.0.1:{stale_server.port}", TcpTransport("127.0.0.1", stale_server.port)
    )
    async with client:
        assert [await client.read(f"ASK {i}") for i in range(20)] == [[i] for i in range(20)]
        assert client.stats.errors == 0 and client.stats.requests == 20
    assert stale_server.connections == 1


# -- E71 codec: reused request bytes, one-step decoding of a normal 01H answer -------------------
_D0 = parse_address("D0")
_M0 = parse_address("M0")
_READ = ReadWords(_D0, 3)
_REQUESTS = [_READ, _READ, ReadWords(_D0, 1), ReadBits(_M0, 4), _READ]
_answers = st.sampled_from(
    [
        b"\x81\x00\x01\x00\x02\x00\x03\x00",  # normal, 3 words
        b"\x81\x00\x01\x00",  # normal, 1 word
        b"\x80\x00\x11",  # normal 00H, 4 bits
        b"\x81\x5b\x10\x00",  # 5BH + abnormal code + trailer
        b"\x81\x5b\x10",  # 5BH without trailer (Q series)
        b"\x81\x51",  # error end code
        b"\x82\x00",  # wrong subheader
        b"\x00",
        b"\x81",
    ]
)


@settings(max_examples=400, deadline=None)
@given(
    answers=st.lists(_answers, min_size=1, max_size=6),
    cuts=st.lists(st.integers(0, 40), max_size=5),
    tail=st.binary(max_size=4),
)
def test_e71_fast_paths_decide_as_the_general_path(
    answers: list[bytes], cuts: list[int], tail: bytes
) -> None:
    stream = b"".join(answers) + tail
    cuts = [c for c in cuts if c <= len(stream)]
    assert _decode_all(True, _REQUESTS, stream, cuts) == _decode_all(False, _REQUESTS, stream, cuts)


def test_e71_reused_request_bytes_are_its_encoding() -> None:
    codec = E71ClientConnection("binary")
    first = codec.send(_READ)
    assert codec.send(_READ) is first  # reused...
    assert first == encode_request(_READ, Code.BINARY)  # ...and what the encoder gives
    other = ReadWords(_D0, 3, pc=0x01)
    assert codec.send(other) == encode_request(other, Code.BINARY) != first


async def test_e71_cached_word_read_follows_pc_and_timer_changes() -> None:
    """The client's cache of checked reads keys on (address, count) and compares the header
    fields on every call: a changed ``pc`` or ``monitoring_timer`` is sent as changed."""
    sim = await sim_e71.start()
    try:
        async with connect(sim.url) as plc:
            assert isinstance(plc, E71Client)
            sent: list[bytes] = []
            send = plc.transport.write

            def spy(data: bytes) -> None:
                sent.append(bytes(data))
                send(data)

            plc.transport.write = spy  # type: ignore[method-assign]
            first = await plc.read("D0", 4)
            assert await plc.read("D0", 4) == first
            timer = plc.monitoring_timer + 1
            plc.monitoring_timer = timer
            assert await plc.read("D0", 4) == first
            assert sent[0] == sent[1] != sent[2]
            assert sent[2] == encode_request(ReadWords(_D0, 4, pc=plc.pc, timer=timer), Code.BINARY)
            with pytest.raises(AddressError):
                await plc.read("D0", 300)  # checks still run for an uncached read
    finally:
        await sim.aclose()


# -- the poller's batch iterator -------------------------------------------------------------------
async def test_poller_batches_give_the_samples_iteration_gives() -> None:
    from tests.test_poll_engine import make, tag

    poller, _ = make({f"p{i}": [tag("w", "D0", count=4)] for i in range(5)}, interval=0.005)
    await poller.start()
    seen: list[Any] = []
    async with asyncio.timeout(10):
        async for batch in poller.batches():
            assert batch, "never an empty batch"
            seen += batch
            if len(seen) >= 50:
                break
    assert all(s.quality.name == "GOOD" for s in seen)
    await eventually(lambda: poller.queue.items, "more samples wait in the buffer")
    await poller.aclose()
    buffered = list(poller.queue.items)
    assert buffered, "the test needs scans left in the buffer"
    rest = [s async for batch in poller.batches() for s in batch]  # ends: the poller is closed
    assert rest == flatten(buffered)

    # the same buffer through the sample iterator
    again, _ = make({"p0": [tag("w", "D0", count=4)]}, interval=0.005)
    again.queue.put(buffered)
    await again.aclose()
    assert [s async for s in again] == flatten(buffered)


async def test_batches_that_wait_gather_more_and_lose_nothing() -> None:
    """``batches(wait=...)``: fewer, larger batches; together exactly the samples, in order,
    per PLC in scan order; the iteration still ends when the poller closes."""
    from tests.test_poll_engine import make, tag

    poller, _ = make({f"p{i}": [tag("w", "D0", count=4)] for i in range(5)}, interval=0.005)
    await poller.start()
    quick: list[list[Any]] = []
    gathered: list[list[Any]] = []
    async with asyncio.timeout(10):
        async for batch in poller.batches():
            quick.append(batch)
            if len(quick) == 10:
                break
        async for batch in poller.batches(wait=0.05):
            assert batch, "never an empty batch"
            gathered.append(batch)
            if len(gathered) == 3:
                break
    # 5 PLCs scanning every 5 ms: a 50 ms wait gathers several scans of each
    assert min(len(b) for b in gathered) > max(len(b) for b in quick)
    seen = [s for b in quick + gathered for s in b]
    for plc in {s.plc for s in seen}:
        times = [s.source_time for s in seen if s.plc == plc]
        assert times == sorted(times)
    await poller.aclose()
    async with asyncio.timeout(5):  # ends while or after waiting, with what was buffered
        rest = [s async for batch in poller.batches(wait=0.05) for s in batch]
    assert poller.pending() == 0 and all(s.quality.name == "GOOD" for s in rest)
    with pytest.raises(ValueError):
        await anext(poller.batches(wait=float("nan")))


# -- AS511: the transaction's overall bound without an asyncio.timeout context --------------------
async def test_as511_chattering_line_still_ends_at_the_transaction_bound() -> None:
    """A peer that never stops sending keeps every per-byte deadline alive; the transaction's
    overall bound (checked after each chunk since issue 16) must still end the request."""

    async def chatter(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError, asyncio.CancelledError):
            while True:
                writer.write(b"\x00")
                await writer.drain()
                await asyncio.sleep(0.01)

    server = await asyncio.start_server(ends_quietly(chatter), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with connect(f"as511+tcp://127.0.0.1:{port}?timeout=0.3") as plc:
            with pytest.raises(PlcError):  # the first byte is no DLE: the transaction aborts
                await plc.read("DB1.DW0", 1)
            # the next one waits for the line's silence after an abort (B5.5), which never
            # comes; a hang would end in the outer bound's TimeoutError, which is no PlcTimeout
            with pytest.raises(PlcTimeout, match="stuck"):
                async with asyncio.timeout(10):
                    await plc.read("DB1.DW0", 1)
    finally:
        server.close()


# -- the poller's shared scan timer against asyncio.sleep ----------------------------------------
@settings(max_examples=30, deadline=None)
@given(
    offsets=st.lists(st.integers(0, 40), min_size=1, max_size=25),
    cancel=st.sets(st.integers(0, 24), max_size=5),
)
def test_ticker_wakes_in_due_order_never_early(offsets: list[int], cancel: set[int]) -> None:
    from plcstack.poll.ticker import Ticker

    async def run() -> None:
        clock = time.perf_counter
        ticker = Ticker(asyncio.get_running_loop(), clock, 0.0)
        start = clock()
        dues = [start + ms / 1000 for ms in offsets]
        woke: list[tuple[int, float]] = []

        async def waiter(i: int) -> None:
            await ticker.wait_until(dues[i])
            woke.append((i, clock()))

        tasks = [asyncio.create_task(waiter(i)) for i in range(len(dues))]
        await asyncio.sleep(0)
        for i in cancel:
            if i < len(tasks):
                tasks[i].cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        alive = [i for i in range(len(dues)) if i not in cancel]
        assert sorted(i for i, _ in woke) == alive
        for i, at in woke:
            # asyncio's timers may fire up to the loop's clock resolution early
            assert at >= dues[i] - 0.002, (i, at - dues[i])
        # woken in due order (ties in any order)
        assert [dues[i] for i, _ in woke] == sorted(dues[i] for i, _ in woke)
        # a cancelled waiter's entry leaves at its time: wait past the latest due (a timer of
        # ours due after the ticker's, so the ticker's runs first however late the loop is)
        await asyncio.sleep(max(max(dues) - clock(), 0.0) + 0.005)
        assert len(ticker) == 0
        ticker.close()

    asyncio.run(run())


async def test_poller_schedule_follows_the_clock() -> None:
    from tests.test_poll_engine import make, tag

    interval = 0.02
    poller, _ = make({f"p{i}": [tag("w", "D0", count=4)] for i in range(20)}, interval=interval)
    loop = asyncio.get_running_loop()
    began, began_wall = loop.time(), time.time()
    await poller.start()
    await asyncio.sleep(0.2)
    # a stall of five ticks, as a loaded machine makes them: counted as overruns, not queued
    time.sleep(0.1)  # noqa: ASYNC251 (the point: the loop blocked)
    await asyncio.sleep(0.2)
    await poller.aclose()
    ticks = (loop.time() - began) / interval  # about 25 at 50 Hz; more if the machine is loaded
    last_end: dict[str, float] = {}
    async for batch in poller.scans():
        for scan in batch:
            last_end[scan.plc] = max(last_end.get(scan.plc, 0.0), scan.receive_time)
    # every tick of the schedule is a scan or, when the scan was late (the stall above, or a
    # loaded machine), an overrun; so their sum follows the clock whatever the load. Never more
    # than the ticks (no scan early, none queued up)...
    kept = {name: (s.scans, s.overruns) for name, s in poller.stats.items()}
    assert all(n + late <= ticks + 1 for n, late in kept.values()), (ticks, kept)
    # ...and every tick up to a PLC's last completed scan is counted: its end moved the schedule
    # past it (less one tick for the first scans' spread, one for rounding). Measured against
    # the poller's own last scan, not the test's clock: a stall right before aclose() is in the
    # clock, but nobody's ticks (the poller never ran during it)
    behind = {
        name: (last_end[name] - began_wall) / interval - (n + late)
        for name, (n, late) in kept.items()
    }
    assert all(b <= 2 for b in behind.values()), behind
    assert all(late >= 3 for _, late in kept.values()), kept  # the stall's missed ticks
    # the scan in flight at aclose() counts as a scan, not a request
    stats = poller.stats.values()
    assert all(s.scans - 1 <= s.requests <= s.scans and s.errors == 0 for s in stats)


# -- E71 codec: take_answer, the whole answer of a poll in one step --------------------------------
def _general_answer(codec: E71ClientConnection, chunk: bytes) -> list[Any]:
    """What the exchange's general path makes of ``chunk``: feed, decode, then look for more."""
    out: list[Any] = []
    try:
        codec.receive_data(chunk)
        event = codec.next_event()
        out.append(event)
        if event is not NEED_DATA:
            out.append(codec.next_event())
    except PlcError as exc:
        out.append(("error", type(exc).__name__, str(exc)))
    return out


def _quick_answer(codec: E71ClientConnection, chunk: bytes) -> list[Any]:
    try:
        event = codec.take_answer(chunk)
    except PlcError as exc:  # it must never raise: the general path reports
        return [("take_answer raised", type(exc).__name__, str(exc))]
    if event is None:
        return _general_answer(codec, chunk)
    return [event, NEED_DATA]


@settings(max_examples=400, deadline=None)
@given(
    before=st.lists(st.tuples(st.sampled_from(_REQUESTS), _answers), max_size=3),
    leftover=st.binary(max_size=3),
    request=st.sampled_from(_REQUESTS),
    chunk=st.one_of(_answers, st.binary(max_size=10)),
    then=_answers,
)
def test_e71_take_answer_decides_as_the_general_path(
    before: list[tuple[Any, bytes]], leftover: bytes, request: Any, chunk: bytes, then: bytes
) -> None:
    """Whatever came before (answers, a 5BH trailer owed, bytes left over), ``take_answer``
    either gives what feeding, decoding and finding nothing more gives, or takes nothing; and
    the codec goes on exactly alike."""
    runs = []
    for take in (_quick_answer, _general_answer):
        codec = E71ClientConnection("binary", transport="tcp")
        out: list[Any] = []
        try:
            for req, answer in before:
                out.append(codec.send(req))
                out += _general_answer(codec, answer)
            codec.receive_data(leftover)
            out.append(codec.send(request))
            out += take(codec, chunk)
            out.append(codec.send(_READ))
            out += _general_answer(codec, then)
        except PlcError as exc:
            out.append(("error", type(exc).__name__, str(exc)))
        runs.append(out)
    assert runs[0] == runs[1]


def test_e71_take_answer_takes_the_normal_answer_to_one_word_read() -> None:
    codec = E71ClientConnection("binary", transport="tcp")
    codec.send(_READ)
    event = codec.take_answer(b"\x81\x00\x01\x00\x02\x00\x03\x00")
    assert event is not None and event.values == (1, 2, 3)
    assert codec.pending == 0 and codec.next_event() is NEED_DATA
    codec.send(_READ)
    assert codec.take_answer(b"\x81\x00\x01\x00\x02\x00") is None  # short: general path
    assert codec.pending == 1
