"""The callback exchange (``Client.start_read``: the exchange driver with a callback) decides
exactly as the awaited one (``await client.read``), over real loopback sockets.

Every case plays one script through a twin peer for each path: a warm-up read the general way
(it connects and fills the E71 client's cache of checked word reads, which ``start_read``
needs), the read under test (awaited, or started with a ``done`` callback), then a follow-up
read. The outcomes (values, or exception type and text), the client's counters, how many chunks
the answer came in, whether the connection stayed open and how many connections the peer saw
must be the same on both paths; and ``done`` must run exactly once.

Also: when ``start_read`` must refuse (and send nothing), single flight with awaited
requests, and ``abandon_exchange``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
from collections.abc import Callable, Sequence
from typing import Any, Literal

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.clients.e71 import E71Client
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code, E71ServerConnection
from plcstack.codecs.e71_commands import DECODERS
from plcstack.sim import e71 as sim_e71
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.transports import Backoff, TcpTransport
from plcstack.transports.tcp import _TcpProtocol
from plcstack.transports.udp import UdpTransport, _UdpProtocol
from tests.aio_helpers import ends_quietly, eventually

Kind = Literal["tcp", "udp"]
#: one step of a scripted answer: bytes to send, seconds to pause, or None to close (TCP)
Step = bytes | float | None
#: the script of one answer, given the bytes of the normal answer to the request
Reply = Callable[[bytes], Sequence[Step]]
#: what a read gave: ("ok", values) or (exception type, its text with the peer's port masked)
Outcome = tuple[str, Any]

WORDS = [0x1234, 0, 0xFFFF, 7]


def _memory() -> MelsecMemory:
    memory = MelsecMemory()
    memory.write_words("D", 0, WORDS)
    return memory


class ScriptedE71:
    """An E71 peer (binary 1E frame, TCP or UDP) that answers each request as ``replies`` says
    (the next one for each request; the normal answer when none is left), so that odd answers
    (split, with extra bytes, error end codes, a close mid-answer, none at all) can be played
    identically to twin clients."""

    def __init__(self, kind: Kind) -> None:
        self.kind = kind
        self.memory = _memory()
        self.replies: list[Reply] = []
        self.received: list[bytes] = []  # every request's bytes, in order
        self.sources: set[object] = set()
        self.playing = 0  # scripts being played now
        self.closed = 0  # connections this peer ended (its close, or the client's seen)
        self._tasks: set[asyncio.Task[None]] = set()
        self._server: asyncio.Server | None = None
        self._udp: asyncio.DatagramTransport | None = None
        self.port = 0

    @property
    def connections(self) -> int:
        return len(self.sources)

    async def start(self) -> ScriptedE71:
        loop = asyncio.get_running_loop()
        if self.kind == "tcp":
            self._server = await asyncio.start_server(ends_quietly(self._serve), "127.0.0.1", 0)
            self.port = self._server.sockets[0].getsockname()[1]
        else:
            peer = self

            class Endpoint(asyncio.DatagramProtocol):
                codec = E71ServerConnection(Code.BINARY, transport="udp", extensions=DECODERS)

                def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
                    peer.sources.add(addr)
                    self.codec.receive_data(data)
                    event = self.codec.next_event()
                    if event is NEED_DATA:  # pragma: no cover - a datagram is one request
                        return
                    peer.received.append(data)
                    normal = self.codec.send(sim_e71.execute(peer.memory, event, Code.BINARY))
                    peer._spawn(peer._play_udp(peer._script(normal), addr))

            transport, _ = await loop.create_datagram_endpoint(
                Endpoint, local_addr=("127.0.0.1", 0)
            )
            self._udp = transport
            self.port = self._udp.get_extra_info("sockname")[1]
        return self

    def _script(self, normal: bytes) -> Sequence[Step]:
        return self.replies.pop(0)(normal) if self.replies else [normal]

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _play_udp(self, steps: Sequence[Step], addr: tuple[str | Any, int]) -> None:
        self.playing += 1
        try:
            for step in steps:
                if isinstance(step, bytes) and self._udp is not None:
                    self._udp.sendto(step, addr)
                elif isinstance(step, float):
                    await asyncio.sleep(step)
        finally:
            self.playing -= 1

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.sources.add(writer.get_extra_info("peername"))
        codec = E71ServerConnection(Code.BINARY, extensions=DECODERS)
        try:
            while data := await reader.read(4096):
                codec.receive_data(data)
                while (event := codec.next_event()) is not NEED_DATA:
                    self.received.append(data)
                    normal = codec.send(sim_e71.execute(self.memory, event, Code.BINARY))
                    self.playing += 1
                    try:
                        for step in self._script(normal):
                            if step is None:
                                return
                            if isinstance(step, bytes):
                                writer.write(step)
                                with contextlib.suppress(ConnectionError):
                                    await writer.drain()
                            else:
                                await asyncio.sleep(step)
                    finally:
                        self.playing -= 1
        except ConnectionError:
            pass
        finally:
            writer.close()
            self.closed += 1

    async def idle(self) -> None:
        """Wait until every script has been played to its end."""
        await eventually(lambda: self.playing == 0, "the peer played its scripts")

    async def aclose(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._server is not None:
            self._server.close()
        if self._udp is not None:
            self._udp.close()


def make_client(peer: ScriptedE71 | Any, kind: Kind, timeout: float = 1.0) -> E71Client:
    """An E71 client to ``peer`` with the same name whatever the port (texts compare equal)."""
    transport = (
        TcpTransport("127.0.0.1", peer.port)
        if kind == "tcp"
        else UdpTransport("127.0.0.1", peer.port)
    )
    return E71Client(
        f"e71+{kind}://plc",
        transport,
        timeout=timeout,
        backoff=Backoff(initial=0.01, maximum=0.02, jitter=0.0),
    )


def _outcome(result: object, port: int) -> Outcome:
    if isinstance(result, BaseException):
        return type(result).__name__, str(result).replace(str(port), "PORT")
    return "ok", result


class Done:
    """A ``done`` callback that counts its calls and resolves a future with the first."""

    def __init__(self) -> None:
        self.calls: list[object] = []
        self.future: asyncio.Future[object] = asyncio.get_running_loop().create_future()

    def __call__(self, result: object) -> None:
        self.calls.append(result)
        if not self.future.done():
            self.future.set_result(result)

    async def result(self) -> object:
        return await asyncio.wait_for(asyncio.shield(self.future), 10)


async def read_awaited(
    client: E71Client, port: int, address: str = "D0", count: int = 4
) -> Outcome:
    try:
        return _outcome(await client.read(address, count), port)
    except Exception as exc:
        return _outcome(exc, port)


async def read_callback(
    client: E71Client, port: int, address: str = "D0", count: int = 4, *, check: bool = True
) -> Outcome:
    """``start_read`` (it must say True) and the result ``done`` got. ``check``: then see that
    ``done`` is not called again (the caller checks that itself otherwise, later)."""
    done = Done()
    assert client.start_read(address, count, done), "the callback path was not taken"
    _started.append(done)
    result = await done.result()
    if check:
        await asyncio.sleep(0.02)  # a second call would come from the loop: give it its chance
        assert len(done.calls) == 1, done.calls
    return _outcome(result, port)


#: every ``Done`` of ``read_callback`` (checked for one call at the end of ``play``)
_started: list[Done] = []


async def play(
    path: str, kind: Kind, script: Sequence[Reply], timeout: float = 1.0, *, fresh: bool = False
) -> Any:
    """The warm-up read, the read under test on ``path``, the follow-up read: what each gave,
    with the counters and the connection state after each."""
    peer = await ScriptedE71(kind).start()
    client = make_client(peer, kind, timeout)
    # chunks as the transport received them (a prepared read takes the plain answer without
    # the client's general step, so they are counted below both paths): their bytes are
    # compared between the paths, their number only checked by the cases (the loop may take
    # two of the peer's writes in one read when the machine is busy)
    chunks: list[int] = []
    tcp_received, udp_received = _TcpProtocol.buffer_updated, _UdpProtocol.datagram_received

    def tcp_counting(protocol: _TcpProtocol, nbytes: int) -> None:
        chunks.append(nbytes)
        tcp_received(protocol, nbytes)

    def udp_counting(protocol: _UdpProtocol, data: bytes, addr: tuple[str | bytes, int]) -> None:
        chunks.append(len(data))
        udp_received(protocol, data, addr)

    _TcpProtocol.buffer_updated = tcp_counting  # type: ignore[method-assign, assignment]
    _UdpProtocol.datagram_received = udp_counting  # type: ignore[method-assign, assignment]
    record: list[Any] = []

    def state(outcome: Outcome) -> None:
        stats = dataclasses.asdict(client.stats)
        # and whether the connection has proven itself (an answer) and how often fresh ones
        # failed before one did: the failure policy's backoff depends on them
        proof = (client.unproven, client._unproven_failures)
        is_open = client.transport.is_open
        record.append((outcome, stats, is_open, peer.connections, len(chunks), proof, sum(chunks)))
        chunks.clear()

    try:
        state(await read_awaited(client, peer.port))
        if fresh:  # the read under test is the first exchange on a new connection
            client.transport.abort()
            await client.open()
        peer.replies.extend(script)
        _started.clear()
        closed = peer.closed
        if path == "callback":
            outcome = await read_callback(client, peer.port, check=False)
        else:
            outcome = await read_awaited(client, peer.port)
        assert not client._lock.locked()
        # the state once whatever the peer sent last has reached us (the bytes after an answer
        # and the end of stream come in their own time)
        await peer.idle()
        if peer.closed > closed:  # the peer closed: the end of stream reaches us in its own time
            await eventually(lambda: not client.transport.is_open, "the client saw the close")
        await eventually(
            lambda: not client.transport.is_open or not client.transport.input_waiting(),
            "the peer's last bytes are delivered",
        )
        state(outcome)
        state(await read_awaited(client, peer.port))
        await peer.idle()
        record.append(len(peer.received))
        # done ran exactly once, also when more came after the answer, or a deadline passed
        assert [len(d.calls) for d in _started] == ([1] if path == "callback" else [])
    finally:
        _TcpProtocol.buffer_updated = tcp_received  # type: ignore[method-assign]
        _UdpProtocol.datagram_received = udp_received  # type: ignore[method-assign]
        await client.aclose()
        await peer.aclose()
    return record


async def differential(
    kind: Kind, script: Sequence[Reply], timeout: float = 1.0, *, fresh: bool = False
) -> Any:
    """Play ``script`` on both paths; they must agree. Returns the record (of either)."""
    awaited = await play("awaited", kind, script, timeout, fresh=fresh)
    called = await play("callback", kind, script, timeout, fresh=fresh)
    assert _compared(called) == _compared(awaited)
    assert awaited[0][0] == ("ok", WORDS)  # the warm-up read
    return awaited


def _compared(record: list[Any]) -> list[Any]:
    """A record without its chunk counts (the bytes stay)."""
    return [r[:4] + r[5:] if isinstance(r, tuple) else r for r in record]


def _split(normal: bytes) -> list[Step]:
    return [normal[:1], 0.005, normal[1:5], 0.005, normal[5:]]


# (name, script of the read under test, transports it applies to)
CASES: list[tuple[str, Reply, tuple[Kind, ...]]] = [
    ("normal", lambda n: [n], ("tcp", "udp")),
    ("split", _split, ("tcp",)),
    ("extra bytes", lambda n: [n + b"\x81\x00"], ("tcp", "udp")),
    ("error end code", lambda n: [b"\x81\x56"], ("tcp", "udp")),
    ("undocumented end code", lambda n: [b"\x81\x25"], ("tcp", "udp")),
    ("close mid-answer", lambda n: [n[:3], 0.005, None], ("tcp",)),
    ("second datagram", lambda n: [n[:3], 0.005, n[3:]], ("udp",)),
]


@pytest.mark.parametrize(("kind", "name"), [(k, name) for name, _, kinds in CASES for k in kinds])
async def test_callback_read_decides_as_the_awaited_read(kind: Kind, name: str) -> None:
    script = next(s for n, s, _ in CASES if n == name)
    record = await differential(kind, [script])
    (outcome, stats, is_open, _, chunks, _, _) = record[1]
    follow_up = record[2]
    assert follow_up[0] == ("ok", WORDS), follow_up  # the client always recovers
    kind_, text = outcome
    # what each case is about, so that the comparison above is not between two wrong runs
    if name == "normal":
        assert outcome == ("ok", WORDS) and is_open and chunks == 1
    elif name == "split":
        assert outcome == ("ok", WORDS) and is_open and chunks == 3
    elif name == "extra bytes" and kind == "tcp":
        assert kind_ == "RemoteProtocolError" and "not trusted" in text and not is_open
    elif name == "error end code":
        assert kind_ == "PlcErrorResponse" and "56H" in text and is_open
        assert stats["errors"] == 1 and follow_up[3] == 1  # the connection was kept
    elif name == "undocumented end code":
        assert kind_ == "RemoteProtocolError" and "25H" in text and not is_open
    elif name == "close mid-answer":
        assert kind_ == "ConnectionLost" and not is_open and follow_up[3] == 2
    else:  # UDP: extra bytes in the datagram, an answer over two datagrams
        assert kind_ != "ok"
    assert record[-1] == 3  # the peer saw three requests: nothing sent twice


@pytest.mark.parametrize("kind", ["tcp", "udp"])
async def test_no_answer_within_the_deadline_is_the_same_timeout(kind: Kind) -> None:
    record = await differential(kind, [lambda n: [0.3, n]], timeout=0.1)
    (kind_, text), stats, is_open, _, chunks, _, _ = record[1]
    assert kind_ == "PlcTimeout" and "within 0.1 s" in text and not is_open and chunks == 0
    assert stats["timeouts"] == 1
    assert record[2][0] == ("ok", WORDS) and record[2][3] == 2  # reconnected


@pytest.mark.parametrize(
    ("kind", "name"),
    [("tcp", "normal"), ("udp", "normal"), ("tcp", "close mid-answer"), ("tcp", "extra bytes")],
)
async def test_on_a_fresh_connection_the_answer_or_failure_counts_alike(
    kind: Kind, name: str
) -> None:
    """The read under test is the first exchange of a new connection: an answer proves the
    connection (the backoff starts over), a close or garbage before any answer counts towards
    backing off; both paths must leave the same proof state (compared in every record)."""
    script = next(s for n, s, _ in CASES if n == name)
    record = await differential(kind, [script], fresh=True)
    (outcome, _, _, connections, _, proof, _) = record[1]
    assert connections == 2  # the read under test did run on the new connection
    if name == "normal":
        assert outcome == ("ok", WORDS) and proof == (False, 0)
    else:
        assert outcome[0] != "ok" and proof == (True, 1)


async def test_callback_reads_follow_each_other() -> None:
    """Every read after a plain answer is taken the callback way again (the answer left the
    codec settled and the lock free), each counted once, on one connection."""
    peer = await ScriptedE71("tcp").start()
    client = make_client(peer, "tcp", 1.0)
    try:
        assert await read_awaited(client, peer.port) == ("ok", WORDS)
        for _ in range(5):
            assert await read_callback(client, peer.port) == ("ok", WORDS)
        assert client.stats.requests == 6 and client.stats.errors == 0
        assert peer.connections == 1 and len(peer.received) == 6
    finally:
        await client.aclose()
        await peer.aclose()


_tails = st.sampled_from([b"", b"\x81\x00", b"\x00", b"\x81\x56", b"\x80\x00\x01"])


@settings(max_examples=15, deadline=None)
@given(
    cuts=st.lists(st.integers(1, 11), max_size=4, unique=True),
    tail=st.one_of(_tails, st.binary(min_size=1, max_size=4)),
    close=st.booleans(),
)
def test_any_chunking_and_garbage_decide_alike(cuts: list[int], tail: bytes, close: bool) -> None:
    """The answer (10 bytes) with ``tail`` after it, cut into TCP chunks at ``cuts``; the peer
    closes after it when ``close``: both paths give the same everything."""

    def script(normal: bytes) -> list[Step]:
        stream = normal + tail
        bounds = [0, *sorted(c for c in cuts if c < len(stream)), len(stream)]
        steps: list[Step] = []
        for a, b in itertools.pairwise(bounds):
            steps += [stream[a:b], 0.003]
        return [*steps, None] if close else steps

    asyncio.run(differential("tcp", [script], timeout=1.0))


# -- when start_read must refuse: nothing sent, nothing counted ------------------------------
@pytest.fixture
async def sim() -> Any:
    simulator = await sim_e71.start(_memory())
    yield simulator
    await simulator.aclose()


def _refuses(client: E71Client, sim: Any, address: str = "D0", count: int = 4) -> None:
    before = (dataclasses.asdict(client.stats), sim.requests)
    done = Done()
    assert not client.start_read(address, count, done)
    assert (dataclasses.asdict(client.stats), sim.requests) == before
    assert done.calls == []


async def test_refused_while_the_lock_is_held(sim: Any) -> None:
    async with make_client(sim, "tcp") as client:
        assert await client.read("D0", 4) == WORDS
        assert client._lock.try_acquire()
        _refuses(client, sim)
        client._lock.release()
        # a write in flight holds it too
        sim.delay = 0.05
        write = asyncio.create_task(client.write("D10", [5]))
        await eventually(lambda: sim.requests == 2, "the write reached the PLC")
        _refuses(client, sim)
        await write
        sim.delay = 0.0
        assert await read_callback(client, sim.port) == ("ok", WORDS)


@pytest.mark.parametrize("where", ["delivered", "in-kernel"])
async def test_refused_while_stale_bytes_wait(where: str) -> None:
    peer = await ScriptedE71("tcp").start()
    try:
        async with make_client(peer, "tcp") as client:
            assert await client.read("D0", 4) == WORDS
            peer.replies.append(lambda n: [n, 0.02, b"\x81\x00"])  # a late second answer
            assert await client.read("D0", 4) == WORDS
            transport = client.transport
            socket = transport._transport  # type: ignore[attr-defined]
            assert isinstance(socket, asyncio.ReadTransport)
            if where == "in-kernel":
                # the peer writes from this loop, so a blocked loop would block it too: the
                # loop stops reading this socket instead (before the late answer, 20 ms away)
                socket.pause_reading()
            await peer.idle()
            if where == "delivered":
                await eventually(
                    lambda: not transport.quiet() and not transport.input_waiting(),
                    "the late answer is delivered",
                )
            else:
                await eventually(transport.input_waiting, "the late answer is in the kernel")
                assert transport.take_received() == []  # not delivered
            requests = len(peer.received)
            before = dataclasses.asdict(client.stats)
            done = Done()
            assert not client.start_read("D0", 4, done)
            assert dataclasses.asdict(client.stats) == before and len(peer.received) == requests
            assert done.calls == []
            if where == "in-kernel":
                socket.resume_reading()
            # the general path finds them and reconnects; then the callback path again
            assert await client.read("D0", 4) == WORDS
            assert peer.connections == 2 and client.stats.errors == 1
            assert await read_callback(client, peer.port) == ("ok", WORDS)
    finally:
        await peer.aclose()


async def test_refused_while_the_codec_is_not_settled(sim: Any) -> None:
    async with make_client(sim, "tcp") as client:
        assert await client.read("D0", 4) == WORDS
        client.exchange_driver.settled = False  # as after an exchange that left bytes in the codec
        _refuses(client, sim)
        assert await client.read("D0", 4) == WORDS  # the general path settles it
        assert await read_callback(client, sim.port) == ("ok", WORDS)


async def test_refused_when_not_connected(sim: Any) -> None:
    async with make_client(sim, "tcp") as client:
        assert await client.read("D0", 4) == WORDS
        client.transport.abort()
        _refuses(client, sim)
        assert not client.transport.is_open
        assert await client.read("D0", 4) == WORDS  # reconnects
        assert await read_callback(client, sim.port) == ("ok", WORDS)


@pytest.mark.parametrize("kind", ["tcp", "udp"])
async def test_refused_for_a_read_never_done_once(kind: Kind) -> None:
    simulator = await sim_e71.start(_memory(), transport=kind)
    try:
        async with make_client(simulator, kind) as client:
            await client.open()
            _refuses(client, simulator)  # connected, but the cache is empty
            assert await client.read("D0", 4) == WORDS
            _refuses(client, simulator, "D0", 3)  # another count: another read
            assert await client.read("M0", 4) == [False] * 4
            _refuses(client, simulator, "M0", 4)  # bit reads are never cached
            assert await read_callback(client, simulator.port) == ("ok", WORDS)
            assert client.stats.requests == 3
    finally:
        await simulator.aclose()


async def test_refused_when_the_header_fields_changed(sim: Any) -> None:
    """The cached request carries ``pc`` and the monitoring timer: after a change the read must
    be sent as changed, so the callback path (which reuses the cached request) says False."""
    async with make_client(sim, "tcp") as client:
        assert await client.read("D0", 4) == WORDS
        client.monitoring_timer += 1
        _refuses(client, sim)
        client.monitoring_timer -= 1
        client.pc = 0x00
        _refuses(client, sim)
        client.pc = 0xFF
        assert await read_callback(client, sim.port) == ("ok", WORDS)


# -- single flight, abandon ---------------------------------------------------------------------
async def test_awaited_requests_queue_behind_a_callback_read(sim: Any) -> None:
    async with make_client(sim, "tcp") as client:
        assert await client.read("D0", 4) == WORDS
        wire: list[str] = []
        send = client.transport.write

        def spy(data: bytes) -> None:
            wire.append(f"sent {data[0]:02X}")
            send(data)

        client.transport.write = spy  # type: ignore[method-assign]
        sim.delay = 0.05
        order: list[str] = []
        done = Done()
        done.future.add_done_callback(lambda _: order.append("callback read"))
        assert client.start_read("D0", 4, done)

        async def write() -> None:
            await client.write("D0", [1, 2])
            order.append("write")

        async def read() -> None:
            order.append(f"read {await client.read('D0', 4)}")

        tasks = [asyncio.create_task(write()), asyncio.create_task(read())]
        await asyncio.sleep(0.02)
        assert wire == ["sent 01"]  # the write waits for the lock, it does not interleave
        assert await done.result() == WORDS
        await asyncio.gather(*tasks)
        assert order == ["callback read", "write", f"read {[1, 2, *WORDS[2:]]}"]
        assert wire == ["sent 01", "sent 03", "sent 01"]
        assert len(done.calls) == 1 and not client._lock.locked()
        assert sim.requests == 4


@pytest.mark.parametrize("kind", ["tcp", "udp"])
async def test_abandoned_exchange_never_calls_done(kind: Kind) -> None:
    simulator = await sim_e71.start(_memory(), transport=kind)
    try:
        async with make_client(simulator, kind) as client:
            assert await client.read("D0", 4) == WORDS
            simulator.delay = 0.05
            done = Done()
            assert client.start_read("D0", 4, done)
            assert client._lock.locked()
            client.abandon_exchange()
            assert not client.transport.is_open and not client._lock.locked()
            client.abandon_exchange()  # nothing in flight: nothing happens
            await asyncio.sleep(0.1)  # the answer would have come by now
            assert done.calls == []
            simulator.delay = 0.0
            assert await client.read("D0", 4) == WORDS  # reconnects
            assert await read_callback(client, simulator.port) == ("ok", WORDS)
            assert client.stats.errors == 0
    finally:
        await simulator.aclose()
