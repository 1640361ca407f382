"""AS511 timing by arrival: an event loop that stalls past the 500 ms character timeout does
not fail a transaction whose bytes came in time, on either side of the line; a silent peer
still times out.

The peer runs on an event loop of its own (a thread), as a PLC or a PG on the far side of a
cable is never held up by our loop; one test stalls a loop both sides share, as the in-process
simulators of the demo and the tests do.
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from contextlib import asynccontextmanager, contextmanager
from typing import Any, TypeVar

import pytest

from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.codecs import as511
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import AGConnection, AGState, PGConnection, PGState, Timeout
from plcstack.errors import PlcTimeout
from plcstack.sim import as511 as sim_as511
from plcstack.transports.tcp import TcpTransport

T = TypeVar("T")

#: longer than the character timeout (0.5 s) by more than half of it
STALL = 1.2


class LoopThread:
    """An event loop on a thread of its own: the far side of the line."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()

    def run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run ``coro`` on that loop and wait for its result."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout=10)

    def stall(self, seconds: float) -> None:
        """Block that loop for ``seconds`` (a long callback, a process not scheduled)."""
        self.loop.call_soon_threadsafe(time.sleep, seconds)

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout=10)
        self.loop.close()


@contextmanager
def far_pty_sim(**options: object) -> Iterator[tuple[LoopThread, sim_as511.PtySimulator]]:
    """An AS511 simulator on a pty, served by a loop on another thread."""
    far = LoopThread()
    sim = far.run(sim_as511.start_pty(**options))  # type: ignore[arg-type]
    try:
        yield far, sim
    finally:
        far.run(sim.aclose())
        far.stop()


@asynccontextmanager
async def client(url: str, **options: object) -> AsyncIterator[AS511Client]:
    plc = connect(url, **options)  # type: ignore[arg-type]
    assert isinstance(plc, AS511Client)
    async with plc:
        yield plc


def stall(seconds: float) -> None:
    """Block the calling thread's event loop for ``seconds``: on purpose, the fault under test."""
    time.sleep(seconds)


async def until(condition: Callable[[], bool], what: str, limit: float = 10.0) -> None:
    """Wait (polling the loop every millisecond) until ``condition`` holds."""
    deadline = time.monotonic() + limit
    while not condition():
        assert time.monotonic() < deadline, f"never: {what}"
        await asyncio.sleep(0.001)


# -- the codecs --------------------------------------------------------------------------------
def test_pg_held_up_takes_bytes_that_waited_and_restarts_the_wait() -> None:
    pg = PGConnection(char_timeout=0.5)
    pg.submit(as511.read_job(0, 4), 10.0)
    pg.data_to_send()
    pg.held_up(10.2)  # before the deadline: nothing changes
    assert pg.deadline == pytest.approx(10.5)
    pg.held_up(11.7)  # the driver's loop stalled past it and saw no silence
    assert pg.deadline == pytest.approx(12.2)
    pg.receive_data(bytes([0x10, 0x06]), 11.7)
    assert pg.state is PGState.W_STX1 and pg.next_event() is NEED_DATA
    # without it, bytes seen that late are late: the transaction is dead
    late = PGConnection(char_timeout=0.5)
    late.submit(as511.read_job(0, 4), 10.0)
    late.receive_data(bytes([0x10, 0x06]), 11.7)
    assert late.next_event() == Timeout(0x04, "W_ACK1")


def test_ag_held_up_takes_bytes_that_waited() -> None:
    ag = AGConnection(char_timeout=0.5)
    ag.receive_data(bytes([0x02]), 0.0)
    assert ag.state is AGState.W_FN and ag.deadline == pytest.approx(0.5)
    ag.held_up(1.4)
    ag.receive_data(bytes([0x04]), 1.4)
    assert ag.data_to_send() == bytes([0x10, 0x06, 0x02])  # DLE ACK, then STX: function taken
    stale = AGConnection(char_timeout=0.5)
    stale.receive_data(bytes([0x02]), 0.0)
    stale.receive_data(bytes([0x04]), 1.4)
    assert stale.state is AGState.IDLE  # a gap: the CPU dropped the transaction


# -- the transport -----------------------------------------------------------------------------
@asynccontextmanager
async def tcp_pair() -> AsyncIterator[tuple[TcpTransport, socket.socket]]:
    """A connected :class:`TcpTransport` and the plain socket at its far end."""
    loop = asyncio.get_running_loop()
    listener = socket.create_server(("127.0.0.1", 0))
    listener.setblocking(False)
    transport = TcpTransport("127.0.0.1", listener.getsockname()[1])
    try:
        opening = asyncio.ensure_future(transport.open(5.0))
        peer, _ = await loop.sock_accept(listener)
        try:
            await opening
            yield transport, peer
        finally:
            peer.close()
    finally:
        transport.abort()
        listener.close()


async def test_an_expired_read_deadline_takes_what_waits_in_the_kernel() -> None:
    """The deadline's timer runs in the same loop pass as a stalled callback during which the
    answer came: the data callback has not run yet, the kernel holds the bytes. The read
    returns them; it does not time out."""
    loop = asyncio.get_running_loop()
    async with tcp_pair() as (transport, peer):
        deadline = loop.time() + 0.3
        # a callback overruns the deadline, so that the next pass runs the answering
        # callback and the deadline's timer together, with no poll of the sockets between
        loop.call_at(deadline - 0.1, time.sleep, 0.2)
        loop.call_at(deadline - 0.001, peer.send, b"answer")
        assert await transport.read(deadline) == b"answer"
        arrived = transport.arrived
        assert arrived is not None and arrived >= deadline


async def test_a_silent_peer_still_times_out_at_the_deadline() -> None:
    loop = asyncio.get_running_loop()
    async with tcp_pair() as (transport, _):
        with pytest.raises(TimeoutError):
            await transport.read(loop.time() + 0.1)


# -- the link and the simulator ------------------------------------------------------------------
async def test_a_stalled_pg_loop_does_not_fail_a_512_byte_read_at_9600_baud() -> None:
    data = bytes(range(256)) * 2
    # the far AG waits 3 s for our DLE ACK after its data frame: this test is about the PG
    with far_pty_sim(baud=9600, char_timeout=3.0) as (_, sim):
        sim.memory.write_absolute(0x6000, data)
        async with client(sim.url) as plc:
            reading = asyncio.ensure_future(plc.read_absolute(0x6000, 512))
            await until(lambda: plc.pg.state is PGState.RX_DATA, "the data frame begun")
            await asyncio.sleep(0.1)  # some of it received
            stall(STALL)  # this loop stalls; the AG goes on sending
            assert await reading == data
            assert plc.stats.errors == 0 and plc.stats.timeouts == 0


@pytest.mark.slow
async def test_a_stalled_ag_loop_does_not_drop_a_512_byte_write_at_9600_baud() -> None:
    data = bytes(range(255, -1, -1)) * 2
    with far_pty_sim(baud=9600) as (far, sim):
        # the PG waits 3 s for the AG to take and execute the job: this test is about the AG
        async with client(sim.url, response_timeout=3.0) as plc:
            writing = asyncio.ensure_future(plc.write_absolute(0x6000, data))
            await until(lambda: plc.pg.state is PGState.W_ACK2, "the parameter frame sent")
            far.stall(STALL)  # the simulator's loop stalls while the parameters arrive
            await writing
            assert plc.stats.errors == 0
        assert sim.memory.read_absolute(0x6000, 512) == data


async def test_a_loop_both_sides_share_stalls_mid_read() -> None:
    """The in-process simulator stalls with the PG: neither side's timer may count the stall
    as the other's silence."""
    data = bytes(range(256)) * 2
    async with await sim_as511.start_pty(baud=9600) as sim, client(sim.url) as plc:
        sim.memory.write_absolute(0x6000, data)
        reading = asyncio.ensure_future(plc.read_absolute(0x6000, 512))
        await until(lambda: plc.pg.state is PGState.RX_DATA, "the data frame begun")
        await asyncio.sleep(0.1)
        stall(STALL)
        assert await reading == data
        assert plc.stats.errors == 0


@pytest.mark.slow
async def test_a_silent_ag_still_times_out_after_a_stall() -> None:
    with far_pty_sim() as (_, sim):
        async with client(sim.url, char_timeout=0.3, nak_backoff=0.05) as plc:
            assert await plc.read("MB0") == [0]
            sim.machine.mute = True
            reading = asyncio.ensure_future(plc.read("MB0"))
            await until(lambda: plc.pg.state is PGState.W_ACK1, "the STX sent")
            stall(STALL)
            with pytest.raises(PlcTimeout, match="DLE ACK after STX"):
                await reading


async def test_a_busy_loop_does_not_slow_the_emulated_line() -> None:
    """Every sleep of a loaded loop wakes late; the simulator's line-rate emulation counted
    each piece from then, so 33 pieces of a 512-byte write made the line a second slow and the
    PG (right to expect 9600 baud) timed out waiting for DLE ACK: the failure of the suite
    under load. The emulated line runs from when the bytes arrived."""
    loop = asyncio.get_running_loop()
    busy = True

    def hog() -> None:  # 40 ms of every 45 the loop is busy elsewhere
        if busy:
            stall(0.04)
            loop.call_later(0.005, hog)

    data = bytes(range(256)) * 2
    async with await sim_as511.start_pty(baud=9600) as sim, client(sim.url) as plc:
        loop.call_soon(hog)
        try:
            await plc.write_absolute(0x6000, data)
        finally:
            busy = False
        assert sim.memory.read_absolute(0x6000, 512) == data
        assert plc.stats.errors == 0
