"""The AS511 face: an S5's programming port on TCP, in front of its one connection, so an
engineer's programming software reaches the S5 through plcstack while the poller goes on.

A programming port has one master. Put plcstack on it and the engineer's PG software (through
the virtual COM port of a serial device server driver, or any tool that speaks AS511 over TCP)
could no longer go online without taking the poller off. With this face it does not have to:
the face is the AG to the PG (:class:`~plcstack.codecs.as511.ServerConnection`, byte by byte),
and each transaction the PG completes is run as one transaction on the PLC's AS511 connection,
in its turn beside the scans (:class:`~plcstack.clients.share.SharedConnection`); the answer
(the AG's data frame, byte for byte, or its DLE NAK) goes back to the PG.

Functions (B.7): 18h system parameters, 1Ah B_INFO, 04h read memory and 1Bh block list go
through as they are. 03h write memory writes anywhere in the 64 KiB address space (blocks,
process images, system data), so it needs ``AS`` (or ``*``) in ``writable``; 1Eh operating
mode (stop, restart) needs ``*``. Anything else is refused the way the AG refuses a function it
does not have: DLE NAK at the function code. A transaction the PLC refused, did not answer, or
that waited longer than ``max_wait`` for its turn is answered with DLE NAK too (the PG tries
again, as after an AG busy); a write is told to ``on_write`` with what may have happened.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from typing import Final

from plcstack.clients.as511 import AS511Client
from plcstack.clients.share import SharedConnection, TurnRefused
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import AGConnection, AGState, Idled, Request
from plcstack.codecs.as511_jobs import (
    FN_B_INFO,
    FN_BLOCK_LIST,
    FN_OPERATING_MODE,
    FN_READ,
    FN_SYSTEM_PARAMETERS,
    FN_WRITE,
    FUNCTION_NAMES,
    READ_PREFIX,
    Job,
    read_job,
)
from plcstack.errors import AddressError, ConnectFailed, PlcError, PlcErrorResponse
from plcstack.gateway.allow import WriteAllowList
from plcstack.gateway.record import FaceWrite, WriteHook
from plcstack.sim.as511 import AgLine
from plcstack.sim.base import DEFAULT_IDLE_TIMEOUT, TcpSimulator, check_idle_timeout
from plcstack.sim.s5store import ABSOLUTE
from plcstack.transports import tap
from plcstack.transports.guard import FaceGuard, Limits, Visit

__all__ = ["As511Executor", "As511Face", "start"]

log = logging.getLogger("plcstack.gateway.as511")

#: the functions a PG gets through the face (the rest: DLE NAK at the function code)
FUNCTIONS: Final = frozenset(
    {FN_SYSTEM_PARAMETERS, FN_B_INFO, FN_READ, FN_BLOCK_LIST, FN_WRITE, FN_OPERATING_MODE}
)
#: a programming port has one master; a second PG is turned away
DEFAULT_MAX_CONNECTIONS = 1
#: the longest read one 04h may ask for (B.7.3 [R], the simulator's limit)
MAX_READ = 4096

#: what the face answers instead of a transaction: the data frame, None (no data frame) or
#: False (DLE NAK)
Answer = bytes | None | bool


def job_of(fn: int, params: bytes) -> Job | None:
    """The PG's transaction as a job for the PLC's connection (None: not a valid one)."""
    if fn == FN_SYSTEM_PARAMETERS and not params:
        return Job(fn, b"", True, None)
    if fn == FN_B_INFO and len(params) == 2:
        return Job(fn, params, True, 13)
    if fn == FN_READ and len(params) == 4:
        start, end = struct.unpack(">HH", params)
        if start <= end and end - start + 1 <= MAX_READ:
            return Job(fn, params, True, READ_PREFIX + end - start + 1)
        return None
    if fn == FN_BLOCK_LIST and len(params) == 1:
        return Job(fn, params, True, None)
    if fn == FN_WRITE and len(params) > 2:
        start = (params[0] << 8) | params[1]
        if start + len(params) - 2 <= 0x10000:
            return Job(fn, params, False, None)
        return None
    if fn == FN_OPERATING_MODE and len(params) == 1 and params[0] <= 2:
        return Job(fn, params, params[0] != 0, 1 if params[0] else None)
    return None


class As511Executor:
    """Runs each PG transaction on the PLC behind ``share`` (see the module docstring)."""

    def __init__(
        self,
        share: SharedConnection,
        *,
        writable: WriteAllowList | None = None,
        on_write: WriteHook | None = None,
        read_previous: bool = False,
    ) -> None:
        client = share.client
        if not isinstance(client, AS511Client):
            raise AddressError(f"{client.name}: an AS511 face needs an AS511 PLC (as511:)")
        self.share = share
        self.client: AS511Client = client
        self.writable = writable if writable is not None else WriteAllowList()
        self.on_write = on_write
        self.read_previous = read_previous
        self.transactions = 0
        self.refused = 0

    def allows(self, fn: int) -> bool:
        """Whether ``writable`` lets the PG run a changing function (03h: AS, 1Eh: ``*``)."""
        if fn == FN_WRITE:
            return self.writable.allows(ABSOLUTE)
        if fn == FN_OPERATING_MODE:
            return str(self.writable) == str(WriteAllowList.parse("*"))
        return True

    async def execute(self, fn: int, params: bytes, peer: str | None) -> Answer:
        """The answer to one transaction of the PG at ``peer``."""
        self.transactions += 1
        job = job_of(fn, params)
        changes = fn in (FN_WRITE, FN_OPERATING_MODE)
        where, value = _what_changes(fn, params)
        if job is None or not self.allows(fn):
            self.refused += 1
            if changes:
                why = "not allowed" if job is not None else "not a valid request"
                self._record(
                    peer, where, value, None, "write_denied", False,
                    f"{where}: {why} (writable: {self.writable}); DLE NAK",
                )  # fmt: skip
            return False
        client = self.client
        what = f"as511 face, {FUNCTION_NAMES.get(fn, f'{fn:02X}h')} for {peer or 'a PG'}"
        sent = False
        previous: list[int] | None = None

        async def run() -> bytes:
            nonlocal sent, previous
            if changes and fn == FN_WRITE and self.read_previous:
                start = (params[0] << 8) | params[1]
                before = await client.transact(read_job(start, len(params) - 2), what)
                previous = list(before[READ_PREFIX:])
            sent = True
            return await client.transact(job, what, is_write=changes)

        try:
            data = await self.share.run(peer if peer is not None else asyncio.current_task(), run)
        except (PlcError, TurnRefused) as exc:
            self.refused += 1
            refused = isinstance(exc, PlcErrorResponse)
            if changes:
                may = sent and not refused and not isinstance(exc, ConnectFailed)
                code = "plc_refused" if refused else "plc_timeout"
                self._record(peer, where, value, previous, code, may, f"{where}: {exc}")
            log.info("as511 face: %s", exc)
            return False
        except asyncio.CancelledError:
            if changes:
                self._record(
                    peer, where, value, previous, "cancelled", sent,
                    f"{where}: the PG went away" + ("; its outcome is unknown" if sent else ""),
                )  # fmt: skip
            raise
        if changes:
            self._record(peer, where, value, previous, "ok", True, f"{where}: confirmed by the PLC")
        return data if job.has_response else None

    def _record(
        self,
        peer: str | None,
        where: str,
        value: list[int],
        previous: list[int] | None,
        result: str,
        may: bool,
        message: str,
    ) -> None:
        if self.on_write is not None:
            self.on_write(FaceWrite("as511", peer, where, value, previous, result, may, message))


def _what_changes(fn: int, params: bytes) -> tuple[str, list[int]]:
    """How a changing function is named in the write record, and its value."""
    if fn == FN_WRITE and len(params) >= 2:
        return f"{(params[0] << 8) | params[1]:04X}h", list(params[2:])
    return "operating mode", list(params)


class As511Face(TcpSimulator):
    """A running AS511 face on TCP: one PG at a time (a programming port has one master);
    ``guard`` (its limits: a first transaction within the first request's deadline, the idle
    timeout) counts what it refused and closed."""

    def __init__(
        self,
        server: asyncio.Server,
        executor: As511Executor,
        guard: FaceGuard,
        *,
        char_timeout: float,
    ) -> None:
        super().__init__(server, "as511+tcp", guard=guard)
        self.executor = executor
        self.char_timeout = char_timeout

    async def serve(self, line: AgLine, transport: asyncio.Transport, visit: Visit) -> None:
        """The AG of one PG: its transactions until it goes (or sends no transaction in time
        after connecting, or is idle too long)."""
        peer = visit.peer
        loop = asyncio.get_running_loop()
        ag = AGConnection(char_timeout=self.char_timeout, functions=FUNCTIONS)
        pending: asyncio.Task[Answer] | None = None
        try:
            while True:
                if pending is not None:
                    # the PLC works on it: the line is watched meanwhile (a PG that sends or
                    # goes now has given the transaction up)
                    reading = asyncio.ensure_future(line.read(None))
                    await asyncio.wait({reading, pending}, return_when=asyncio.FIRST_COMPLETED)
                    if pending.done():
                        reading.cancel()
                        await asyncio.gather(reading, return_exceptions=True)
                        answer = pending.result()
                        pending = None
                        if ag.state is AGState.EXECUTE:
                            if answer is False:
                                ag.refuse(loop.time())
                            else:
                                data = answer if isinstance(answer, bytes) else None
                                ag.respond(data, loop.time())
                            transport.write(ag.data_to_send())
                        continue
                    data = reading.result()
                else:
                    deadline = ag.deadline if ag.deadline is not None else visit.due
                    try:
                        data = await line.read(deadline)
                    except TimeoutError:
                        now = loop.time()
                        if ag.deadline is None:
                            if visit.expired() is not None:  # counted and said by the guard
                                return
                            continue
                        ag.timer(now)
                        continue
                if not data:
                    return  # the PG went away
                visit.touch()
                now = line.arrived or loop.time()
                ag.held_up(now)
                ag.receive_data(data, now)
                while (event := ag.next_event()) is not NEED_DATA:
                    if isinstance(event, Request):
                        visit.served()
                        pending = asyncio.ensure_future(
                            self.executor.execute(event.fn, event.params, peer)
                        )
                    elif isinstance(event, Idled) and pending is not None:
                        pending.cancel()  # the PG broke off: not sent if it still waits
                        await asyncio.gather(pending, return_exceptions=True)
                        pending = None
                out = ag.data_to_send()
                if out:
                    transport.write(out)
        except (ConnectionError, OSError, asyncio.CancelledError):
            return
        finally:
            if pending is not None:
                pending.cancel()
                await asyncio.gather(pending, return_exceptions=True)
            visit.leave()
            await line.close(transport)


async def start(
    executor: As511Executor,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    max_connections: int = DEFAULT_MAX_CONNECTIONS,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    char_timeout: float = 0.5,
    limits: Limits | None = None,
) -> As511Face:
    """Serve the AS511 face of ``executor``'s PLC on ``host:port`` (0: any free port):
    ``limits`` (the face's table keys), or ``max_connections`` PGs and ``idle_timeout``."""
    if limits is None:
        limits = Limits(max_connections, idle_timeout=check_idle_timeout(idle_timeout))
    guard = FaceGuard("as511", f"AS511 face {host}:{port}", limits, log)
    faces: list[As511Face] = []

    def connected(line: AgLine, transport: asyncio.Transport) -> None:
        visit = guard.admit(transport.get_extra_info("peername"))
        if visit is None:
            transport.abort()
            return
        task = asyncio.get_running_loop().create_task(faces[0].serve(line, transport, visit))
        faces[0].track(task)

    server = await tap.create_server(lambda: AgLine(f"{host}:{port}", connected), host, port)
    face = As511Face(server, executor, guard, char_timeout=char_timeout)
    faces.append(face)
    return face
