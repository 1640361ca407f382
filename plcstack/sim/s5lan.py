"""Siemens S5-LAN-LINK module simulator (26-byte request block over TCP) on the shared S5Memory.

Behaves like the module of spec part A: one connection at a time (a further connection is
accepted and closed at once, D.A4), strict request/response in order, the Err codes of A.7 in the
A.7 check order, and optionally the module's answer time of 50 ms + 1.5 ms per data byte.

[R] A.11 mapping onto :class:`~plcstack.sim.s5memory.S5Memory`: D -> DB blocks, X -> DX blocks
(``Start`` = data word number), M/E/I/A/O -> the flag, input and output areas (``Start`` = byte
number, also for words: D.A3), T and Z/C -> timer/counter words (``Start`` = timer/counter number).
Word data travel low byte first and are stored big-endian (the module swaps, A.6).

The default memory (when ``start(memory=None)``) holds DB1...DB10 and DX1...DX2 with 256 data words
each, all zero, so ``plcstack read s5lan://127.0.0.1:PORT DB10.DW5 20`` works out of the box.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
from collections.abc import Callable
from typing import Any

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.s5lan import (
    DEFAULT_VERSION,
    ERR_NO_AREA,
    ERR_OK,
    BadRequest,
    ByteOrder,
    Header,
    Request,
    ServerConnection,
    estimate_seconds,
    swap_words,
)
from plcstack.sim.base import (
    DEFAULT_IDLE_TIMEOUT,
    ClientGone,
    TcpSimulator,
    add_guard_arguments,
    close_writer,
    limits_of,
    module_guard,
)
from plcstack.sim.s5memory import Area, BlockType, S5Memory
from plcstack.sim.s5store import S5Fault, S5Store, Target, memory_of, resolve_store
from plcstack.transports import tap
from plcstack.transports.guard import FaceGuard, FrameDeadline, Limits, Visit, earliest

__all__ = ["DEFAULT_DATA_WORDS", "S5LanSimulator", "add_cli_arguments", "default_memory", "start"]

#: data words of each default DB/DX
DEFAULT_DATA_WORDS = 256
DEFAULT_CLI_PORT = 5010

_AREAS: dict[str, Area] = {
    "M": Area.FLAGS,
    "E": Area.INPUTS,
    "I": Area.INPUTS,
    "A": Area.OUTPUTS,
    "O": Area.OUTPUTS,
    "T": Area.TIMERS,
    "Z": Area.COUNTERS,
    "C": Area.COUNTERS,
}


def default_memory() -> S5Memory:
    """DB1..DB10 and DX1..DX2, 256 zero data words each."""
    mem = S5Memory(default_dbs=dict.fromkeys(range(1, 11), DEFAULT_DATA_WORDS))
    for number in (1, 2):
        mem.create_block(BlockType.DX, number, DEFAULT_DATA_WORDS)
    return mem


class S5LanSimulator(TcpSimulator):
    """A running module. ``memory`` is live: tests may read and change it while clients work."""

    def __init__(self, server: asyncio.Server, state: _State) -> None:
        super().__init__(server, "s5lan", guard=state.guard)
        #: where requests are executed: the simulated CPU, or the AS511 gateway's real one
        self.store: S5Store = state.store
        self._state = state

    @property
    def memory(self) -> S5Memory:
        """The simulated CPU image (only for a module started on one, not for a gateway)."""
        return memory_of(self.store, "S5-LAN")

    @property
    def active_connections(self) -> int:
        return self.guard.current

    def inject_error(self, err: int, times: int = 1) -> None:
        """Answer the next ``times`` well-formed requests with ``err`` (e.g. 9 = PLC timeout)."""
        self._state.injected.extend([err] * times)

    def close_clients(self) -> None:
        """Drop every client connection now (like a module reset); the listener stays."""
        for writer in list(self._state.writers):
            writer.transport.abort()


class _State:
    def __init__(
        self,
        store: S5Store,
        guard: FaceGuard,
        *,
        realistic_timing: bool,
        data_timeout: float,
        header_byte_order: ByteOrder,
        strict: bool,
        version: int,
    ) -> None:
        self.store = store
        #: connections at once and per host, first request, idle: what they refused and closed
        self.guard = guard
        self.realistic_timing = realistic_timing
        self.data_timeout = data_timeout
        self.header_byte_order: ByteOrder = header_byte_order
        self.strict = strict
        self.version = version
        self.injected: collections.deque[int] = collections.deque()
        self.writers: set[asyncio.StreamWriter] = set()

    # -- executing a valid request on the store (A.7 steps 5..8) ---------------------------
    async def execute(self, req: Request, peer: str | None = None) -> tuple[int, bytes]:
        """Answer one well-formed request from the store: ``(Err, data)``; ``peer`` is the
        client's address, handed to the store with a write (the gateway audits it).

        The same code serves the simulator (a :class:`MemoryStore`) and the AS511 gateway (the
        real CPU behind its programming port): one server implementation for both.
        """
        h = req.header
        if self.injected:
            return self.injected.popleft(), b""
        n = h.data_len or 0
        target: Target
        try:
            if h.area in ("D", "X"):
                if not 1 <= h.db <= 255:
                    return ERR_NO_AREA, b""  # DB 0 holds the block address list (A.5)
                target = (BlockType.DB if h.area == "D" else BlockType.DX, h.db)
                offset = 2 * h.start
                swap = True
            else:
                target = _AREAS[h.area]
                offset = 2 * h.start if target in (Area.TIMERS, Area.COUNTERS) else h.start
                swap = h.data_type == "W"
            if h.is_read:
                raw = await self.store.read(target, offset, n, peer=peer)
                return ERR_OK, swap_words(raw) if swap else raw
            data = swap_words(req.data) if swap else req.data
            await self.store.write(target, offset, data, peer=peer)
            return ERR_OK, b""
        except S5Fault as exc:
            return exc.s5lan_err, b""


async def _handle(
    state: _State, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
) -> None:
    visit = state.guard.admit(writer.get_extra_info("peername"))
    if visit is None:
        # D.A4: the module supports one connection; the extra one is closed at once so the
        # second client fails fast instead of waiting for an answer that never comes.
        await close_writer(writer)
        return
    state.writers.add(writer)
    # a gateway's request of a client that went away is given up where it waits (never sent)
    gone = ClientGone(reader, writer)
    codec = ServerConnection(
        header_byte_order=state.header_byte_order, strict=state.strict, version=state.version
    )
    # A request begun (header or write data) must be complete within data_timeout of its first
    # byte (A.7, Err 10 for write data): measured per read, a client sending one byte every
    # half second held the module's connection for ever.
    frame = FrameDeadline(state.data_timeout)
    loop = asyncio.get_running_loop()
    try:
        while True:
            # An incomplete header is given as long and then the connection is closed (the
            # module has no error code for it); a connection that sends no request in time
            # after connecting, or nothing for idle_timeout, is closed, or the one connection
            # the module accepts would be held by a silent socket for ever.
            frame.note(codec.awaiting_data or codec.buffered > 0)
            due = frame.due
            try:
                async with asyncio.timeout_at(earliest(due, visit.due)):
                    data = await reader.read(65536)
            except TimeoutError:
                if due is not None and loop.time() >= due:
                    if codec.awaiting_data:
                        late = codec.data_timeout()
                        if not await _answer(state, codec, writer, late, visit, gone):
                            return
                        continue
                    visit.frame_late()
                    return
                if visit.expired() is not None:
                    return
                continue
            if not data:
                return
            visit.touch()
            codec.receive_data(data)
            while (event := codec.next_event()) is not NEED_DATA:
                if not await _answer(state, codec, writer, event, visit, gone):
                    return
    except (ConnectionError, OSError):
        return
    finally:
        gone.close()
        visit.leave()
        state.writers.discard(writer)
        await close_writer(writer)  # not abort(): an Err 6 answer before a close must go out


async def _answer(
    state: _State,
    codec: ServerConnection,
    writer: asyncio.StreamWriter,
    event: object,
    visit: Visit,
    gone: ClientGone,
) -> bool:
    """Answer one event of the client of ``visit``; ``False`` when the connection must be
    closed."""
    visit.served()
    if isinstance(event, BadRequest):
        if event.close:  # no request block at all: the client's garbage, said once per burst
            visit.malformed(f"a malformed request ({event.reason}); closing the connection")
        writer.write(codec.send_response(event.header, event.err))
        await writer.drain()
        return not event.close
    assert isinstance(event, Request)
    with gone.waiting():
        err, data = await state.execute(event, visit.peer)
    if state.realistic_timing:
        await asyncio.sleep(estimate_seconds(event.header.data_len or 0))
    header: Header = event.header
    writer.write(codec.send_response(header, err, data))
    await writer.drain()
    return True


async def start(
    memory: S5Memory | None = None,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    realistic_timing: bool = False,
    max_connections: int = 1,
    data_timeout: float = 1.0,
    header_byte_order: ByteOrder = "little",
    strict: bool = False,
    version: int = DEFAULT_VERSION,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    store: S5Store | None = None,
    limits: Limits | None = None,
) -> S5LanSimulator:
    """Start a module simulator; returns once it accepts clients (``sim.url`` says where).

    ``store`` executes the requests somewhere else than in a memory image (the AS511 gateway
    passes the real CPU); it excludes ``memory``.

    ``realistic_timing`` delays each answer by 50 ms + 1.5 ms per data byte (A.8);
    ``data_timeout`` is how long write data may take before Err 10 ([R] 1 s);
    ``strict`` accepts only PLCType 35h (D.A2); ``idle_timeout``: seconds after which a
    connection that sent nothing is closed (default 600, ``None``: never). ``limits`` (a
    gateway's face) replaces ``max_connections`` and ``idle_timeout``: see
    :func:`~plcstack.sim.base.module_guard`.
    """
    title = "S5-LAN simulator" if store is None else "S5-LAN face"
    store = resolve_store(memory, store, default_memory)
    guard = module_guard("s5lan", title, max_connections, idle_timeout, limits)
    state = _State(
        store,
        guard,
        realistic_timing=realistic_timing,
        data_timeout=data_timeout,
        header_byte_order=header_byte_order,
        strict=strict,
        version=version,
    )
    sim: S5LanSimulator | None = None
    early: list[asyncio.Task[None]] = []  # accepted before start_server() returned

    def on_connect(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.ensure_future(_handle(state, reader, writer))
        if sim is not None:
            sim.track(task)
        else:
            early.append(task)

    server = await tap.start_server(on_connect, host, port)
    sim = S5LanSimulator(server, state)
    for task in early:
        sim.track(task)
    return sim


# -- CLI ---------------------------------------------------------------------------------------
def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument(
        "--port", type=int, default=DEFAULT_CLI_PORT, help=f"TCP port (default {DEFAULT_CLI_PORT})"
    )
    parser.add_argument(
        "--realistic-timing",
        action="store_true",
        help="delay answers like the module: 50 ms + 1.5 ms per data byte",
    )
    add_guard_arguments(parser, 1)


async def serve_cli(args: argparse.Namespace, announce: Callable[[str], Any]) -> None:
    sim = await start(
        host=args.host,
        port=args.port,
        realistic_timing=args.realistic_timing,
        limits=limits_of(args),
    )
    announce(f"listening on {sim.host}:{sim.port} (TCP)")
    await sim.serve_forever()
