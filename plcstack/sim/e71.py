"""MELSEC A-series E71 simulator (1E frame; binary or ASCII; TCP or UDP).

``sim = await start()`` binds 127.0.0.1 on a free port and returns once clients can connect;
``sim.url`` is the URL to give :func:`plcstack.connect` (``?code=ascii`` included), ``sim.memory``
the :class:`~plcstack.sim.melsec_memory.MelsecMemory` behind it (devices, CPU state, switches).

Every request is answered as an E71 would (spec §10.3 precedence): undefined subheader 50H, ASCII
conversion 54H, PC number other than FFH 5BH/10H (no MELSECNET here), 58H/57H for unit, range and
count errors, 56H for unknown device codes, 55H for writes refused by the CPU state; the
connection survives all of them. The commands beyond 00H-09H (0AH-21H, 39H-3CH, 60H-62H) are
executed by :mod:`plcstack.sim.e71_module` (CPU model, remote RUN/STOP, random access buffer,
special modules, extended file registers, program areas).
"""

from __future__ import annotations

import argparse
import asyncio
import weakref
from collections.abc import Callable
from typing import Any, Literal, cast

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import (
    REQUEST_TYPES,
    Ack,
    BadRequest,
    BitsResponse,
    Code,
    CpuGroup,
    DeviceRef,
    E71ServerConnection,
    ErrorResponse,
    ExtensionRequest,
    ExtensionResponse,
    MonitorBits,
    MonitorWords,
    OpaqueRequest,
    ReadBits,
    ReadWords,
    RegisterMonitorBits,
    RegisterMonitorWords,
    Request,
    Response,
    TestBits,
    TestWords,
    WordsResponse,
    WriteBits,
    WriteWords,
    limit_error,
    unit_error,
)
from plcstack.codecs.e71_commands import DECODERS
from plcstack.codecs.e71_end_codes import GARBAGE_END_CODES
from plcstack.sim.base import (
    DEFAULT_IDLE_TIMEOUT,
    Limits,
    Simulator,
    TcpSimulator,
    UdpSimulator,
    add_guard_arguments,
    limits_of,
    module_guard,
)
from plcstack.sim.e71_module import execute_extension, module_of
from plcstack.sim.melsec_memory import CpuState, MelsecAccessError, MelsecMemory
from plcstack.transports import tap
from plcstack.transports.guard import FaceGuard, Visit

__all__ = [
    "MAX_CONNECTIONS",
    "E71TcpSimulator",
    "E71UdpSimulator",
    "answer",
    "execute",
    "start",
]

#: the module has 8 connections (§1.1); a 9th TCP connection is closed at once
MAX_CONNECTIONS = 8
#: §13 A15: an incomplete TCP request is discarded after this many seconds (no response, 71H)
INCOMPLETE_TIMEOUT = 30.0

_WRITES = (WriteBits, WriteWords, TestBits, TestWords)


def _span(ref: DeviceRef, word_units: bool) -> int:
    return 16 if word_units and ref.device.is_bit else 1


def execute(
    memory: MelsecMemory,
    event: Request | OpaqueRequest | ExtensionRequest | BadRequest,
    code: Code = Code.BINARY,
) -> Response | ExtensionResponse:
    """What the E71 answers to one decoded request (shared by TCP and UDP)."""
    if isinstance(event, ExtensionRequest):
        # 0AH-21H, 39H-3CH, 60H-62H: plcstack.sim.e71_module
        return execute_extension(memory, event, code)
    if isinstance(event, BadRequest):
        if event.pc is not None and event.pc != 0xFF:
            return ErrorResponse(event.command, 0x5B, 0x10)
        return ErrorResponse(event.command, event.end_code)
    if isinstance(event, OpaqueRequest):
        # Defined but not implemented in this version: framed, answered 50H.
        return ErrorResponse(event.command, 0x50)
    cmd = event.COMMAND
    if event.pc != 0xFF:
        # PC 00H-40H address MELSECNET stations; the simulated E71 has no network (5BH/10H).
        return ErrorResponse(cmd, 0x5B, 0x10)
    try:
        return _execute(memory, event)
    except MelsecAccessError as exc:
        return ErrorResponse(cmd, exc.end_code)


def _execute(mem: MelsecMemory, req: Request) -> Response:
    cmd = req.COMMAND
    if isinstance(req, MonitorBits):
        # §13 A10: 08H only after 06H, 09H only after 07H; otherwise 57H.
        if mem.monitor is None or mem.monitor[0] != "bits":
            return ErrorResponse(cmd, 0x57)
        return BitsResponse(cmd, tuple(mem.read_refs_bits(mem.monitor[1])))
    if isinstance(req, MonitorWords):
        if mem.monitor is None or mem.monitor[0] != "words":
            return ErrorResponse(cmd, 0x57)
        return WordsResponse(cmd, tuple(mem.read_refs_words(mem.monitor[1])))
    # §10.3 order: unit/head (58H) -> count (57H) -> span (57H) -> CPU mode (55H).
    if unit_error(req) is not None:
        return ErrorResponse(cmd, 0x58)
    word_units = cmd in (0x01, 0x03, 0x05, 0x07)
    if isinstance(req, (ReadBits, ReadWords, WriteBits, WriteWords)):
        heads = [req.ref]
    elif isinstance(req, (TestBits, TestWords)):
        heads = [p[0] for p in req.points]
    else:
        heads = list(req.refs)
    for ref in heads:
        mem.check(ref.device, ref.number, 1)
    if limit_error(req) is not None:
        return ErrorResponse(cmd, 0x57)
    if isinstance(req, (ReadBits, ReadWords)):
        mem.check(req.ref.device, req.ref.number, req.count * _span(req.ref, word_units))
    elif isinstance(req, (WriteBits, WriteWords)):
        mem.check(req.ref.device, req.ref.number, len(req.values) * _span(req.ref, word_units))
    else:
        for ref in heads:
            mem.check(ref.device, ref.number, _span(ref, word_units))
    if isinstance(req, _WRITES) and not mem.writes_allowed:
        return ErrorResponse(cmd, 0x55)
    ref0 = heads[0]
    if isinstance(req, ReadBits):
        return BitsResponse(cmd, tuple(mem.read_bits(ref0.device, ref0.number, req.count)))
    if isinstance(req, ReadWords):
        return WordsResponse(cmd, tuple(mem.read_words(ref0.device, ref0.number, req.count)))
    if isinstance(req, WriteBits):
        mem.write_bits(ref0.device, ref0.number, req.values)
    elif isinstance(req, WriteWords):
        mem.write_words(ref0.device, ref0.number, req.values)
    elif isinstance(req, TestBits):
        for ref, state in req.points:
            mem.write_bits(ref.device, ref.number, [state])
    elif isinstance(req, TestWords):
        for ref, value in req.points:
            mem.write_words(ref.device, ref.number, [value])
    elif isinstance(req, RegisterMonitorBits):
        mem.monitor = ("bits", req.refs)
    elif isinstance(req, RegisterMonitorWords):
        mem.monitor = ("words", req.refs)
    return Ack(cmd)


def answer(
    memory: MelsecMemory,
    event: Request | OpaqueRequest | ExtensionRequest | BadRequest,
    cpu_time: float,
    code: Code = Code.BINARY,
) -> tuple[Response | ExtensionResponse, float]:
    """The response and after how many seconds it is due, given the CPU needs ``cpu_time``.

    App. B: the E71 waits for the CPU at most the request's ACPU monitoring timer (250 ms units,
    0 = forever); when that expires first it answers 60H and the request is not executed.
    """
    if cpu_time > 0 and isinstance(event, REQUEST_TYPES) and event.pc == 0xFF:
        limit = event.timer * 0.25
        if event.timer and cpu_time > limit:
            return ErrorResponse(event.COMMAND, 0x60), limit
    return execute(memory, event, code), max(cpu_time, 0.0)


class _TcpConnection(asyncio.Protocol):
    def __init__(self, sim: E71TcpSimulator) -> None:
        self.sim = sim
        self.codec = E71ServerConnection(
            sim.code,
            lower_ok=sim.lower_ok,
            abnormal_trailer=sim.abnormal_trailer,
            extensions=DECODERS,
        )
        self.transport: asyncio.Transport | None = None
        self._partial_timer: asyncio.TimerHandle | None = None
        self._busy_until = 0.0  # loop time when the last queued (delayed) answer goes out
        self._visit: Visit | None = None

    def connection_made(self, transport_: asyncio.BaseTransport) -> None:
        # cast, not isinstance: uvloop's transports are not subclasses of asyncio.Transport
        transport = cast(asyncio.Transport, transport_)
        self._visit = self.sim.guard.admit(transport.get_extra_info("peername"), self._expired)
        if self._visit is None:
            transport.abort()  # all 8 connections in use
            return
        self.transport = transport
        self.sim.connections.add(self)
        self.sim.connection_count.opened()

    def _expired(self, reason: str) -> None:
        """No request in time after connecting, or nothing for ``idle_timeout``."""
        if self.transport is not None:
            self.transport.abort()

    def pause_writing(self) -> None:
        # The peer does not read its answers: stop reading its requests until it does, so
        # neither our write buffer nor a backlog of answered requests grows (asyncio calls
        # this above the transport's write high-water mark).
        if self.transport is not None:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

    def data_received(self, data: bytes) -> None:
        transport = self.transport
        if transport is None:
            return
        visit = self._visit
        if visit is not None:
            visit.touch()
        codec = self.codec
        codec.receive_data(data)
        sim = self.sim
        while True:
            event = codec.next_event()
            if event is NEED_DATA:
                break
            sim.requests += 1
            if visit is not None:
                visit.served()
                if isinstance(event, BadRequest) and event.end_code in GARBAGE_END_CODES:
                    visit.malformed(
                        f"a malformed request ({event.reason}; answered {event.end_code:02X}H)"
                    )
            if sim.mute:
                continue
            if sim.delay <= 0 and sim.cpu_time <= 0 and self._busy_until == 0.0:
                transport.write(codec.send(execute(sim.memory, event, sim.code)))
                continue
            response, due = answer(sim.memory, event, sim.cpu_time, sim.code)
            # requests are processed strictly one after another (§4.1): queue behind the last
            loop = asyncio.get_running_loop()
            at = max(loop.time(), self._busy_until) + due + max(sim.delay, 0.0)
            self._busy_until = at
            loop.call_at(at, self._write_late, codec.send(response))
        self._arm_partial_timer()

    def _write_late(self, data: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)
        if self._busy_until <= asyncio.get_running_loop().time():
            self._busy_until = 0.0

    def _arm_partial_timer(self) -> None:
        if self._partial_timer is not None:
            self._partial_timer.cancel()
            self._partial_timer = None
        if self.codec.buffered:
            loop = asyncio.get_running_loop()
            self._partial_timer = loop.call_later(
                self.sim.incomplete_timeout, self.codec.discard_partial
            )

    def connection_lost(self, exc: Exception | None) -> None:
        if self._partial_timer is not None:
            self._partial_timer.cancel()
        if self._visit is not None:
            self._visit.leave()
        if self.transport is not None:
            self.sim.connection_count.closed()
        self.sim.connections.discard(self)
        self.transport = None


class _E71Plc:
    """What the TCP and the UDP E71 simulator share: the PLC behind the module (its memory and
    code), how it answers (latency, CPU time, mute) and the count of requests received."""

    #: seconds added to every answer (network latency); never turns into an end code
    delay = 0.0
    #: seconds the CPU needs per request; beyond the request's monitoring timer -> 60H
    cpu_time = 0.0
    #: swallow requests without answering (a dead link, for timeout tests)
    mute = False

    def _init_plc(self, memory: MelsecMemory, code: Code, abnormal_trailer: bool) -> None:
        self.memory = memory
        self.code = code
        self.abnormal_trailer = abnormal_trailer
        self.requests = 0


class E71TcpSimulator(_E71Plc, TcpSimulator):
    """An E71 on TCP: up to 8 connections at once, one :class:`MelsecMemory` behind all."""

    def __init__(
        self,
        server: asyncio.Server,
        memory: MelsecMemory,
        code: Code,
        *,
        lower_ok: bool,
        abnormal_trailer: bool,
        incomplete_timeout: float,
        guard: FaceGuard,
    ) -> None:
        query = "code=ascii" if code is Code.ASCII else ""
        super().__init__(server, "e71+tcp", query, guard)
        self._init_plc(memory, code, abnormal_trailer)
        self.lower_ok = lower_ok
        self.incomplete_timeout = incomplete_timeout
        self.connections: set[_TcpConnection] = set()

    async def aclose(self) -> None:
        for conn in list(self.connections):
            if conn.transport is not None:
                conn.transport.abort()
        await super().aclose()


class _UdpEndpoint(asyncio.DatagramProtocol):
    def __init__(self, sim_ref: list[E71UdpSimulator], code: Code, lower_ok: bool) -> None:
        self.sim_ref = sim_ref
        self.codec = E71ServerConnection(
            code, transport="udp", lower_ok=lower_ok, extensions=DECODERS
        )
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        if not self.sim_ref or self.transport is None:
            return
        sim = self.sim_ref[0]
        self.codec.abnormal_trailer = sim.abnormal_trailer
        self.codec.receive_data(data)
        event = self.codec.next_event()
        if event is NEED_DATA:  # pragma: no cover - one datagram is always one event
            return
        sim.requests += 1
        if sim.mute:
            return
        response, due = answer(sim.memory, event, sim.cpu_time, sim.code)
        out = self.codec.send(response)
        # §13 A14: reply to the datagram's source address.
        wait = due + max(sim.delay, 0.0)
        if wait > 0:
            asyncio.get_running_loop().call_later(wait, self.transport.sendto, out, addr)
        else:
            self.transport.sendto(out, addr)


class E71UdpSimulator(_E71Plc, UdpSimulator):
    """An E71 on UDP: one message per datagram, answered to its source address."""

    def __init__(
        self,
        transport: asyncio.DatagramTransport,
        memory: MelsecMemory,
        code: Code,
        *,
        abnormal_trailer: bool,
    ) -> None:
        super().__init__(transport, "e71+udp", "code=ascii" if code is Code.ASCII else "")
        self._init_plc(memory, code, abnormal_trailer)


async def start(
    memory: MelsecMemory | None = None,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    code: Code | Literal["binary", "ascii"] = "binary",
    transport: Literal["tcp", "udp"] = "tcp",
    lower_ok: bool = True,
    abnormal_trailer: bool = True,
    incomplete_timeout: float = INCOMPLETE_TIMEOUT,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    limits: Limits | None = None,
) -> E71TcpSimulator | E71UdpSimulator:
    """Start an E71 simulator; returns once it accepts clients (``port=0``: a free port).

    ``lower_ok=False``: lower-case ASCII hex is answered with 54H (§13 A7 strict mode).
    ``abnormal_trailer=False``: 5BH answers without the trailing 00H (Q-series form, §13 A3).
    ``idle_timeout``: seconds (TCP) after which a connection that sent nothing is closed
    (default 600; ``None``: never), so idle sockets cannot hold all 8 connections for ever;
    a connection must send its first request within 10 s. ``limits`` replaces the module's
    8 connections and ``idle_timeout`` (see :func:`~plcstack.sim.base.module_guard`).
    """
    guard = module_guard("e71", "E71 simulator", MAX_CONNECTIONS, idle_timeout, limits)
    mem = memory if memory is not None else MelsecMemory()
    code_ = code if isinstance(code, Code) else Code(code)
    loop = asyncio.get_running_loop()
    if transport == "udp":
        holder: list[E71UdpSimulator] = []
        dtransport, _ = await tap.create_datagram_endpoint(
            lambda: _UdpEndpoint(holder, code_, lower_ok), local_addr=(host, port)
        )
        usim = E71UdpSimulator(dtransport, mem, code_, abnormal_trailer=abnormal_trailer)
        holder.append(usim)
        return usim
    if transport != "tcp":
        raise ValueError(f"transport must be 'tcp' or 'udp', not {transport!r}")
    sims: list[E71TcpSimulator] = []
    server = await tap.create_server(lambda: _TcpConnection(sims[0]), host, port)
    tsim = E71TcpSimulator(
        server,
        mem,
        code_,
        lower_ok=lower_ok,
        abnormal_trailer=abnormal_trailer,
        incomplete_timeout=incomplete_timeout,
        guard=guard,
    )
    sims.append(tsim)

    sim_ref = weakref.ref(tsim)  # the module outlives no simulator through this listener

    def close_on_stop() -> None:
        # §1.3: a remote STOP closes the connections unless buffer word 496 keeps them; the
        # answer 94 00 is flushed first (close, not abort), after the write of this event
        alive = sim_ref()
        if alive is not None:
            loop.call_soon(_close_all, alive)

    module_of(mem).stop_listeners.append(close_on_stop)
    return tsim


def _close_all(sim: E71TcpSimulator) -> None:
    for conn in list(sim.connections):
        if conn.transport is not None:
            conn.transport.close()


# -- CLI: plcstack sim e71 ------------------------------------------------------------------


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=5000, help="port (default 5000; 0 = any)")
    parser.add_argument(
        "--code",
        choices=("binary", "ascii"),
        default="binary",
        help="frame coding the clients must use, like DIP switch SW2 (default binary; "
        "a client sets ?code=ascii)",
    )
    add_guard_arguments(parser, MAX_CONNECTIONS)
    parser.add_argument(
        "--transport",
        choices=("tcp", "udp"),
        default="tcp",
        help="listen on TCP (URL e71+tcp://) or UDP (URL e71+udp://) (default tcp)",
    )
    parser.add_argument(
        "--cpu-group",
        choices=[g.value for g in CpuGroup],
        default="VII",
        help="CPU group, which sets the device ranges "
        "(default VII = A3A/A3U/A4U; plcstack docs e71)",
    )
    parser.add_argument(
        "--state", choices=[s.value for s in CpuState], default="RUN", help="CPU state"
    )
    parser.add_argument(
        "--no-write-in-run",
        action="store_true",
        help="DIP switch SW7/SW3 OFF: writes in RUN are refused with 55H",
    )


async def serve_cli(args: argparse.Namespace, announce: Callable[[str], None]) -> None:
    memory = MelsecMemory(
        args.cpu_group, state=CpuState(args.state), write_in_run=not args.no_write_in_run
    )
    sim: Simulator = await start(
        memory,
        host=args.host,
        port=args.port,
        code=args.code,
        transport=args.transport,
        limits=limits_of(args),
    )
    assert isinstance(sim, (E71TcpSimulator, E71UdpSimulator))
    announce(f"listening on {sim.host}:{sim.port} ({args.transport.upper()})")
    await sim.serve_forever()
