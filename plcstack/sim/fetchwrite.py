"""FETCH/WRITE CP simulator (S5 16-byte header, optionally inside the Tani MK header).

Serves the shared :class:`~plcstack.sim.s5memory.S5Memory` over TCP, with raw or MK framing, on
one port (FETCH and WRITE) or on separate FETCH and WRITE ports, as real CPs are configured.
Bad requests are answered with the protocol's error field (C.6.4); malformed headers close the
connection without an answer (C.6.5). Life acks (MK only) are sent when idle and a client that
stays silent beyond ``life_timeout`` is dropped (C.3).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from typing import Literal

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.fetchwrite import (
    BadRequest,
    FetchRequest,
    FetchResponse,
    OpCode,
    Org,
    ServerConnection,
    WriteRequest,
    WriteResponse,
)
from plcstack.codecs.mk import LifeAckTimer, MkConnection
from plcstack.errors import RemoteProtocolError
from plcstack.sim.base import (
    DEFAULT_IDLE_TIMEOUT,
    DEFAULT_MAX_CONNECTIONS,
    ClientGone,
    TcpSimulator,
    add_guard_arguments,
    limits_of,
    module_guard,
)
from plcstack.sim.s5memory import Area, BlockType, S5Memory
from plcstack.sim.s5store import (
    ABSOLUTE,
    PERIPHERAL,
    FaultKind,
    S5Fault,
    S5Store,
    Target,
    memory_of,
    resolve_store,
)
from plcstack.transports import tap
from plcstack.transports.guard import FRAME_TIMEOUT, FaceGuard, FrameDeadline, Limits, earliest

__all__ = ["FetchWriteSimulator", "add_cli_arguments", "default_memory", "serve_cli", "start"]

log = logging.getLogger(__name__)

DbStartUnit = Literal["word", "byte"]
_Role = Literal["both", "fetch", "write"]

#: byte areas outside blocks, by ORG ID
_BYTE_AREAS: dict[int, Area] = {Org.MB: Area.FLAGS, Org.EB: Area.INPUTS, Org.AB: Area.OUTPUTS}
#: word areas outside blocks (one word per timer/counter/system data word)
_WORD_AREAS: dict[int, Area] = {Org.ZB: Area.COUNTERS, Org.TB: Area.TIMERS, Org.BS: Area.SYSTEM}


def default_memory() -> S5Memory:
    """A CPU image that makes ``plcstack sim fetchwrite`` useful out of the box.

    DB1 (64 words, zero), DB10 (256 words, ``DW(5+i) = 1000h + i`` as in the spec's goldens),
    DB20 (512 words, ``DWn = n``), DX3 (32 words, zero).
    """
    mem = S5Memory(default_dbs={1: 64, 10: 256, 20: 512})
    mem.write_db_words(10, 5, [0x1000 + i for i in range(20)])
    mem.write_db_words(20, 0, list(range(512)))
    mem.create_block(BlockType.DX, 3, 32)
    return mem


class FetchWriteSimulator(TcpSimulator):
    """A running FETCH/WRITE simulator; ``write_port`` is set when WRITE has its own port.

    Test hooks: ``inject_error`` answers every job with that error field; ``silent`` swallows jobs
    (for client timeout tests); ``send_life_acks = False`` stops keep-alives (dead-peer tests).
    """

    def __init__(
        self,
        server: asyncio.Server,
        store: S5Store,
        *,
        mk: bool,
        db_start_unit: DbStartUnit,
        life_ack: float | None,
        life_timeout: float | None,
        strict: bool,
        write_server: asyncio.Server | None,
        guard: FaceGuard,
    ) -> None:
        query = []
        if mk:
            query.append("mk=1")
        if db_start_unit == "byte":
            query.append("db_start=byte")
        self.write_server = write_server
        self.write_port: int | None = None
        if write_server is not None:
            self.write_port = write_server.sockets[0].getsockname()[1]
            query.append(f"write_port={self.write_port}")
        if life_ack is not None:
            query.append(f"life_ack={life_ack:g}")
        super().__init__(server, "fetchwrite", "&".join(query), guard)
        #: where jobs are executed: the simulated CPU, or the AS511 gateway's real one
        self.store = store
        self.mk = mk
        self.db_start_unit: DbStartUnit = db_start_unit
        self.life_ack = life_ack
        self.life_timeout = life_timeout
        self.strict = strict
        self.inject_error: int | None = None
        self.silent = False
        self.send_life_acks = True
        self.connections = 0
        self.jobs = 0
        self.life_acks_received = 0
        self.life_acks_sent = 0
        self.dropped_dead = 0

    @property
    def memory(self) -> S5Memory:
        """The simulated CPU image (only for a simulator started on one, not for a gateway)."""
        return memory_of(self.store, "FETCH/WRITE")

    async def aclose(self) -> None:
        if self.write_server is not None:
            self.write_server.close()
        await super().aclose()
        if self.write_server is not None:
            await self.write_server.wait_closed()

    # -- one connection -----------------------------------------------------------------------
    async def handle(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, role: _Role
    ) -> None:
        visit = self.guard.admit(writer.get_extra_info("peername"))
        if visit is None:
            writer.transport.abort()
            return
        task = asyncio.current_task()
        if task is not None:
            self.track(task)
        self.connections += 1
        # a gateway's job of a client that went away is given up where it waits (never sent)
        gone = ClientGone(reader, writer)
        peer = visit.peer
        loop = asyncio.get_running_loop()
        # a module is lenient with partners that do not count (only strict checks them)
        mk = MkConnection(strict=self.strict, check_seq=self.strict) if self.mk else None
        codec = ServerConnection("mk" if self.mk else "raw", mk=mk)
        timer = LifeAckTimer(
            self.life_ack if self.mk else None,
            self.life_timeout if self.mk else None,
            loop.time(),
        )
        # measured from a job's first byte: the idle timeout restarts with every byte, so a
        # header sent one byte at a time held a connection (of max_connections) for ever
        frame = FrameDeadline(FRAME_TIMEOUT)
        try:
            while True:
                while (event := codec.next_event()) is not NEED_DATA:
                    visit.served()
                    if isinstance(event, BadRequest) and event.close:
                        visit.malformed(f"a job that cannot be framed ({event.reason})")
                    with gone.waiting():
                        response, close = await self.answer(event, role, peer)
                    if self.silent:
                        continue
                    writer.write(codec.send(response))
                    timer.sent(loop.time())
                    if close:
                        return
                    # A peer that does not read its answers is not read either until it does
                    # (drain waits above the write high-water mark): before, answers piled up
                    # (+1.5 GB in 17 s) and a backlog was worked off long after it was gone.
                    await writer.drain()
                if mk is not None:
                    if mk.life_acks_received:
                        visit.served()  # an MK partner keeping the line up is no silent socket
                    self.life_acks_received += mk.life_acks_received
                    mk.life_acks_received = 0
                if self.silent:
                    codec = ServerConnection("mk" if self.mk else "raw", mk=mk)
                frame.note(codec.buffered > 0)
                due = frame.due
                try:
                    async with asyncio.timeout_at(earliest(timer.next_wakeup(), visit.due, due)):
                        data = await reader.read(65536)
                except TimeoutError:
                    now = loop.time()
                    if due is not None and now >= due:
                        visit.frame_late()
                        return
                    if visit.expired() is not None:
                        return
                    if timer.dead(now):
                        self.dropped_dead += 1
                        log.info("fetchwrite sim: no life ack for %s s, closing", timer.timeout)
                        return
                    if timer.ack_due(now):
                        if self.send_life_acks:
                            writer.write(codec.life_ack())
                            self.life_acks_sent += 1
                        timer.sent(now)
                    continue
                if not data:
                    return
                visit.touch()
                timer.received(loop.time())
                codec.receive_data(data)
        except RemoteProtocolError as exc:
            # C.6.5: a malformed header closes the connection without an answer.
            visit.malformed(f"a malformed header ({exc.message}); closing the connection")
        except (ConnectionError, OSError):
            pass
        finally:
            gone.close()
            visit.leave()
            writer.transport.abort()

    async def answer(
        self, event: FetchRequest | WriteRequest | BadRequest, role: _Role, peer: str | None = None
    ) -> tuple[FetchResponse | WriteResponse, bool]:
        """The acknowledgement of one job and whether to close the connection afterwards.

        Executed on ``self.store``: the simulated CPU, or the real one behind the AS511 gateway
        (one server implementation for both); ``peer``, the client's address, goes with a write
        to the store (the gateway audits it).
        """
        self.jobs += 1
        is_fetch = isinstance(event, FetchRequest) or (
            isinstance(event, BadRequest) and event.opcode == OpCode.FETCH_REQUEST
        )

        def ack(error: int, data: bytes = b"") -> FetchResponse | WriteResponse:
            return FetchResponse(error, data) if is_fetch else WriteResponse(error)

        if isinstance(event, BadRequest):  # [R] C.6.4: bad ORG id / length / data amount -> 01
            return ack(event.error), event.close
        if self.inject_error is not None:
            return ack(self.inject_error), False
        # [R] C.6.5: with separate ports, a job type the port does not serve is error 01.
        if role == ("write" if is_fetch else "fetch"):
            return ack(0x01), False
        try:
            if isinstance(event, FetchRequest):
                target, offset, size = self._span(event.org, event.db, event.start, event.length)
                return ack(0, await self.store.read(target, offset, size, peer=peer)), False
            target, offset, _ = self._span(event.org, event.db, event.start, 0)
            await self.store.write(target, offset, event.data, peer=peer)
            return ack(0), False
        except S5Fault as exc:
            return ack(exc.fetchwrite_error), False
        except _Unsupported:
            return ack(0x01), False

    def _span(self, org: int, db: int, start: int, length: int) -> tuple[Target, int, int]:
        """Where a job goes: (target, byte offset, byte length)."""
        if org in (Org.DB, Org.DX):
            if db == 0:
                raise S5Fault(FaultKind.NO_AREA, "DB 0 is not a data block")
            btype = BlockType.DB if org == Org.DB else BlockType.DX
            # [R] C.6.3 / D.C6: DB start is a DW number (Siemens) or, optionally, a byte number.
            offset = start if self.db_start_unit == "byte" else 2 * start
            return (btype, db), offset, 2 * length
        if org in _BYTE_AREAS:
            return _BYTE_AREAS[org], start, length
        if org in _WORD_AREAS:
            return _WORD_AREAS[org], 2 * start, 2 * length
        if org == Org.PB:  # [R] a memory image: reads see the input image, writes the output
            return PERIPHERAL, start, length
        if org == Org.AS:
            # [R] absolute addressing: start is a byte address in the 64 KiB space, length words.
            return ABSOLUTE, start, 2 * length
        raise _Unsupported(org)  # DE, QB: not modelled (D.C5 allows error 01)


class _Unsupported(Exception):
    pass


async def start(
    memory: S5Memory | None = None,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    mk: bool = False,
    db_start_unit: DbStartUnit = "word",
    write_port: int | None = None,
    life_ack: float | None = None,
    life_timeout: float | None = None,
    strict: bool = False,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    max_connections: int = DEFAULT_MAX_CONNECTIONS,
    store: S5Store | None = None,
    limits: Limits | None = None,
) -> FetchWriteSimulator:
    """Start a FETCH/WRITE simulator; returns once it accepts connections.

    ``write_port``: ``None`` serves FETCH and WRITE on ``port``; a number (``0`` = any free
    port) serves FETCH on ``port`` and WRITE on ``write_port``. ``life_ack``: MK keep-alive
    interval in seconds (default off); ``life_timeout`` defaults to 3 x ``life_ack`` (D.C4).
    ``idle_timeout``: seconds after which a connection that sent nothing is closed (default
    600, ``None``: never); ``max_connections``: connections at once (per port), further ones
    are closed at once and counted in ``refused_connections``. ``store`` executes the jobs
    somewhere else than in a memory image (the AS511 gateway passes the real CPU); it excludes
    ``memory``. ``limits`` (a gateway's face) replaces ``max_connections`` and
    ``idle_timeout``: see :func:`~plcstack.sim.base.module_guard`.
    """
    title = "FETCH/WRITE simulator" if store is None else "FETCH/WRITE face"
    guard = module_guard("fetchwrite", title, max_connections, idle_timeout, limits)
    if db_start_unit not in ("word", "byte"):
        raise ValueError("db_start_unit must be 'word' or 'byte'")
    if life_ack is not None and not mk:
        raise ValueError("life acks need the MK header (mk=True)")
    if life_ack is not None and life_timeout is None:
        life_timeout = 3 * life_ack
    store = resolve_store(memory, store, default_memory)
    holder: list[FetchWriteSimulator] = []

    def handler(
        role: _Role,
    ) -> Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]:
        async def run(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            # A connection task ends quietly when the simulator closes: asyncio's stream server
            # would otherwise log the cancellation of its callback task as an error.
            with contextlib.suppress(asyncio.CancelledError):
                await holder[0].handle(reader, writer, role)

        return run

    main_role: _Role = "both" if write_port is None else "fetch"
    server = await tap.start_server(handler(main_role), host, port)
    write_server = None
    if write_port is not None:
        try:
            write_server = await tap.start_server(handler("write"), host, write_port)
        except OSError:
            server.close()
            raise
    sim = FetchWriteSimulator(
        server,
        store,
        mk=mk,
        db_start_unit=db_start_unit,
        life_ack=life_ack,
        life_timeout=life_timeout,
        strict=strict,
        write_server=write_server,
        guard=guard,
    )
    holder.append(sim)
    return sim


# -- CLI -------------------------------------------------------------------------------------


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=5030, help="TCP port (default 5030)")
    add_guard_arguments(parser, DEFAULT_MAX_CONNECTIONS)
    parser.add_argument(
        "--mk",
        action="store_true",
        help="wrap every telegram in the Tani MK header (CPs set up for it)",
    )
    parser.add_argument(
        "--db-start",
        choices=("word", "byte"),
        default="word",
        help="unit of the DB start address: word (Siemens, default) or byte (VIPA-style)",
    )
    parser.add_argument(
        "--write-port", type=int, default=None, help="serve WRITE on this separate port"
    )
    parser.add_argument(
        "--life-ack",
        type=float,
        default=None,
        metavar="SECONDS",
        help="MK life ack interval (needs --mk; dead-peer timeout 3x this)",
    )


async def serve_cli(args: argparse.Namespace, announce: Callable[[str], None]) -> None:
    if args.life_ack is not None and not args.mk:
        raise ValueError("--life-ack needs --mk (life acks exist only in the Tani MK header)")
    sim = await start(
        host=args.host,
        port=args.port,
        mk=args.mk,
        db_start_unit=args.db_start,
        write_port=args.write_port,
        life_ack=args.life_ack,
        limits=limits_of(args),
    )
    line = f"listening on {sim.host}:{sim.port} (TCP)"
    if sim.write_port is not None:
        line = (
            f"listening on {sim.host}:{sim.port} (TCP, FETCH), "
            f"{sim.host}:{sim.write_port} (TCP, WRITE)"
        )
    announce(line)
    await sim.serve_forever()
