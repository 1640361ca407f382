"""The Modbus TCP server in front of the poller: HMI panels and SCADA see the old PLCs as Modbus.

A face of the runtime (:mod:`plcstack.north.pipeline`): ``[modbus]`` in the file of ``plcstack
poll`` (or ``plcstack serve modbus plant.toml``, the same runtime) serves it, fed with the
poller's scans after report-by-exception like every other face. What is answered is in
:mod:`plcstack.north.modbus.service`, how values become registers in
:mod:`plcstack.north.modbus.registers`, the wire format in :mod:`plcstack.north.modbus.frames`
(which says why this is not pymodbus's server).

Each connection answers its requests in the order they came. A read is answered at once, from
the image, inside the data callback; a write runs in a task (the PLC's answer is awaited) and
the requests behind it wait for it. A client that disconnects does not cut a PLC write short:
the write finishes and its outcome is logged.

Requests are taken from a connection's bytes only when they can be answered: while a write
waits for its PLC, or while the client does not read its answers (the transport's write buffer
above its high-water mark), the server stops reading from that client, so what it holds for one
client is bounded (a client that sent reads and never read the answers grew the server by
119 MB in 15 s before). The client that does not read is said once in the log; if it also sends
nothing for ``idle_timeout`` seconds it is dropped. A frame must be complete within
:data:`~plcstack.transports.guard.FRAME_TIMEOUT` seconds of its first byte, a new client must
send its first request within ``first_request_timeout``, and at most ``max_clients`` clients
(``max_clients_per_host`` from one host) are served at once (see
:mod:`plcstack.transports.guard`). Malformed frames are said once per host per burst with
their count: a fuzzing client wrote one WARNING line per frame (3,934 lines, 520 KB for 6,000
frames) before.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

from plcstack.errors import ConfigError, PlcError, RemoteProtocolError
from plcstack.north.face import PlcUpdate, PollerView
from plcstack.north.health import Health
from plcstack.north.modbus.config import MapEntry, ModbusSettings, build_map
from plcstack.north.modbus.frames import (
    ModbusServerConnection,
    Request,
    exception_frame,
    response_frame,
)
from plcstack.north.modbus.service import Refused, RegisterImage, describe_code
from plcstack.north.writes import WritePath
from plcstack.poll.samples import Sample, Scan
from plcstack.resource import AsyncResource
from plcstack.transports.guard import FRAME_TIMEOUT, FaceGuard, FrameDeadline, Visit
from plcstack.transports.peer import peer_address

if TYPE_CHECKING:
    from prometheus_client.core import Metric

__all__ = ["ModbusCollector", "ModbusServer"]

log = logging.getLogger("plcstack.north.modbus")


class _Connection(asyncio.Protocol):
    def __init__(self, server: ModbusServer) -> None:
        self.server = server
        self.codec = ModbusServerConnection()
        self.transport: asyncio.Transport | None = None
        self.writing: asyncio.Task[None] | None = None
        #: the client's address (``host:port``), as the log and the write audit say it
        self.peer: str | None = None
        #: its stay, as the server's guard admitted it (None: refused, or gone)
        self.visit: Visit | None = None
        #: the client does not read: its answers are above the transport's high-water mark
        self.write_blocked = False
        self.said_blocked = False
        self.paused = False
        self.frame: FrameDeadline | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        peername = transport.get_extra_info("peername")
        self.peer = peer_address(peername)
        server = self.server
        self.visit = server.guard.admit(peername, self._expired)
        if self.visit is None:
            transport.abort()
            return
        server.connections.add(self)
        self.frame = FrameDeadline(FRAME_TIMEOUT, self._frame_late)
        log.info("Modbus client %s connected", self.peer or "?")

    def connection_lost(self, exc: Exception | None) -> None:
        self.transport = None
        visit, self.visit = self.visit, None
        if visit is None:
            return
        visit.leave()
        self.server.connections.discard(self)
        if self.frame is not None:
            self.frame.cancel()
        log.info("Modbus client %s disconnected", self.peer or "?")

    def data_received(self, data: bytes) -> None:
        if self.visit is not None:
            self.visit.touch()
        self.codec.receive_data(data)
        self._drain()

    def pause_writing(self) -> None:
        self.write_blocked = True
        if not self.said_blocked and self.transport is not None:
            self.said_blocked = True
            self.server.slow_clients += 1
            log.warning(
                "Modbus client %s does not read its answers (%d bytes waiting); not reading its"
                " requests until it does",
                self.peer or "?",
                self.transport.get_write_buffer_size(),
            )

    def resume_writing(self) -> None:
        self.write_blocked = False
        self._drain()

    def _drain(self) -> None:
        """Answer the requests received, in order, until one is a write (that one runs in a
        task) or the client stops reading; then read more only if nothing waits."""
        server = self.server
        while self.writing is None and not self.write_blocked and self.transport is not None:
            try:
                request = self.codec.next_request()
            except RemoteProtocolError as exc:
                server.protocol_errors += 1
                if self.visit is not None:
                    self.visit.malformed(f"a broken frame ({exc.message}); closing the connection")
                self.drop()
                return
            if request is None:
                break
            if self.visit is not None:
                self.visit.served()
                if request.error:
                    # a well-framed request that is none (unknown function, counts that do not
                    # match): the client's garbage, answered with its exception code
                    self.visit.malformed(
                        f"a malformed request (function {request.function}, answered"
                        f" {describe_code(request.error)})"
                    )
            if request.error == 0 and request.is_write and server.for_us(request):
                task = asyncio.create_task(self._write(request), name="modbus write")
                server.writes_in_flight.add(task)
                task.add_done_callback(self._write_done)
                self.writing = task
                break
            self._send(server.answer_read(request))
        transport = self.transport
        if transport is None or self.frame is None:
            return
        waiting = self.writing is not None or self.write_blocked
        # only a frame the client is still sending has a deadline; requests that wait here
        # for a write or for the client to read are the server's delay, not the client's
        self.frame.note(not waiting and self.codec.buffered > 0)
        if waiting and not self.paused:
            self.paused = True
            transport.pause_reading()
        elif not waiting and self.paused:
            self.paused = False
            transport.resume_reading()

    def drop(self) -> None:
        """End the connection: closed once its answers are out, aborted if they cannot be (a
        client that does not read would hold the connection for ever)."""
        transport = self.transport
        if transport is None:
            return
        if transport.get_write_buffer_size():
            transport.abort()
        else:
            transport.close()

    def _expired(self, reason: str) -> None:
        """The guard's first-request or idle deadline passed (counted and said there)."""
        if reason == "idle_timeout":
            self.server.idle_closed += 1
        self.drop()

    def _frame_late(self) -> None:
        self.server.protocol_errors += 1
        if self.visit is not None:
            self.visit.frame_late()
        if self.transport is not None:
            self.transport.abort()

    async def _write(self, request: Request) -> None:
        self._send(await self.server.answer_write(request, peer=self.peer))

    def _write_done(self, task: asyncio.Task[None]) -> None:
        self.server.writes_in_flight.discard(task)
        self.writing = None
        if not task.cancelled() and task.exception() is not None:
            # answer_write turns every failure into an answer; this is a bug, not a PLC's fault
            log.error("Modbus write task failed", exc_info=task.exception())
            self.drop()
            return
        if self.transport is not None:
            self._drain()

    def _send(self, frame: bytes) -> None:
        if self.transport is not None:
            self.transport.write(frame)


class ModbusServer(AsyncResource):
    """A Modbus TCP server answering from the poller's latest values (see the module); a face
    of the runtime (:class:`~plcstack.north.face.Face`). ``writes``: the run's one write path
    (default: one on ``poller`` without an audit)."""

    name = "modbus"

    def __init__(
        self,
        poller: PollerView,
        settings: ModbusSettings | None = None,
        entries: list[MapEntry] | None = None,
        *,
        writes: WritePath | None = None,
    ) -> None:
        self.poller = poller
        self.settings = settings if settings is not None else ModbusSettings()
        if entries is None:
            entries = build_map({plc: poller.tags(plc) for plc in poller.plcs})
        if not entries:
            raise ConfigError('no tag has a modbus key: map tags with modbus = "hr:N" (ir, co, di)')
        self.image = RegisterImage(entries, self.settings.word_order)
        self.writes = writes if writes is not None else WritePath(poller)
        self.port = self.settings.port
        self.protocol_errors = 0
        #: connections closed because the client sent nothing for ``idle_timeout`` seconds
        self.idle_closed = 0
        #: clients that stopped reading their answers (each said once in the log)
        self.slow_clients = 0
        #: clients at once and per host, first-request and idle deadlines; ``guard.counts``
        #: has what it refused and closed, by reason
        self.guard = FaceGuard("modbus", "Modbus server", self.settings.limits, log)
        self._server: asyncio.Server | None = None
        #: the clients connected now
        self.connections: set[_Connection] = set()
        #: the writes waiting for their PLC (a client that goes away does not cut one short)
        self.writes_in_flight: set[asyncio.Task[None]] = set()

    @classmethod
    def from_config(
        cls,
        poller: PollerView,
        settings: ModbusSettings | None = None,
        *,
        writes: WritePath | None = None,
    ) -> ModbusServer:
        """The server of the poller's tags (their ``modbus`` keys, with file and line in its
        errors) and the ``[modbus]`` table (``settings``; None: the defaults)."""
        tags = {plc: poller.tags(plc) for plc in poller.plcs}
        map_ = build_map(tags, source=poller.config.source)
        return cls(poller, settings or ModbusSettings(), map_, writes=writes)

    @property
    def endpoint(self) -> str:
        """``host:port`` as bound (after :meth:`start`)."""
        host = self.settings.host
        return f"[{host}]:{self.port}" if ":" in host else f"{host}:{self.port}"

    @property
    def clients(self) -> int:
        return len(self.connections)

    def for_us(self, request: Request) -> bool:
        """Whether a request names this server: its ``unit_id``, or 0 or 255, which Modbus TCP
        clients send to a device they address by IP alone."""
        return request.unit in (self.settings.unit_id, 0, 255)

    # -- answers --------------------------------------------------------------------------------
    def _refused(self, request: Request, refused: Refused) -> bytes:
        self.image.exceptions[refused.code] += 1
        # a refused read is DEBUG: a panel polling a dead PLC would flood the log (the poller
        # logs the PLC's failure); refused writes are WARNINGs of the write path or of here;
        # a malformed request was said by the connection's guard, once per burst
        write = request.function in (5, 6, 15, 16)
        said = refused.logged or request.error != 0
        level = logging.WARNING if write and not said else logging.DEBUG
        where = f" {request.table}:{request.address} x{request.count}" if request.known else ""
        log.log(
            level,
            "Modbus FC %d%s answered %s: %s",
            request.function,
            where,
            describe_code(refused.code),
            refused.reason,
        )
        return exception_frame(request, refused.code)

    def answer_read(self, request: Request) -> bytes:
        """The frame answering a read, or any request refused before anything is sent."""
        image = self.image
        image.requests[request.function] += 1
        try:
            if request.error:
                raise Refused(request.error, "malformed or unsupported request")
            if not self.for_us(request):
                raise image.wrong_unit(request, self.settings.unit_id)
            return response_frame(request, image.read(request))
        except Refused as refused:
            return self._refused(request, refused)

    async def answer_write(self, request: Request, *, peer: str | None) -> bytes:
        """The frame answering a write, after the PLC confirmed it (or the refusal); ``peer``
        is the client's address for the write audit."""
        image = self.image
        image.requests[request.function] += 1
        try:
            await image.write(request, self.writes, peer=peer)
        except Refused as refused:
            return self._refused(request, refused)
        return response_frame(request)

    # -- life cycle -----------------------------------------------------------------------------
    async def start(self) -> None:
        if self._server is not None:
            return
        loop = asyncio.get_running_loop()
        host, port = self.settings.host, self.settings.port
        try:
            self._server = await loop.create_server(lambda: _Connection(self), host, port)
        except OSError as exc:
            raise PlcError(
                f"Modbus server cannot listen on {self.settings.endpoint}: {exc.strerror or exc}"
                " (another process on that port? set [modbus] endpoint)"
            ) from None
        self.port = self._server.sockets[0].getsockname()[1]
        self.guard.announce(self.endpoint)

    async def aclose(self) -> None:
        """Stop listening and drop the clients; PLC writes in flight finish (and are logged)."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for connection in list(self.connections):
            connection.drop()
        if self.writes_in_flight:
            await asyncio.gather(*self.writes_in_flight, return_exceptions=True)
        if server is not None:
            await server.wait_closed()
        self.guard.close()

    async def aopen(self) -> None:
        """``async with server`` listens (see :meth:`start`)."""
        await self.start()

    # -- scans in -------------------------------------------------------------------------------
    def submit(self, scans: Sequence[Scan]) -> None:
        """The sinks' common interface: take scans into the image (never blocks)."""
        self.image.update(scans)

    def probe(self, sample: Sample) -> None:
        """Every sample is taken (a value its registers cannot hold reads as an exception)."""

    async def update_plcs(self, update: PlcUpdate) -> None:
        """The registers of a reloaded configuration: a removed PLC's are gone, an added one's
        read as not polled yet until its first scan, every other keeps its value."""
        view = update.view
        tags = {plc.name: view.tags(plc.name) for plc in view.config.plcs}
        self.image.remap(build_map(tags, source=view.config.source))

    def health(self) -> Health:
        if self._server is None:
            return Health(self.name, f"not listening on {self.settings.endpoint}")
        return Health(self.name, figures=(("clients", self.clients),))

    def summary(self) -> str:
        image = self.image
        return (
            f"modbus {self.endpoint}: {sum(image.requests.values())} requests,"
            f" {sum(image.exceptions.values())} exception answers,"
            f" {image.writes_confirmed} writes confirmed"
        )

    def announce(self) -> str:
        return f"Modbus server listening on {self.endpoint}"

    def metrics(self) -> Iterator[Metric]:
        """The server's own figures for ``/metrics`` (see :class:`ModbusCollector`)."""
        return self.collector().collect()

    def collector(self) -> ModbusCollector:
        return ModbusCollector(self)


class ModbusCollector:
    """prometheus-client collector of the server's own figures (register it next to the
    poller's collector): requests by function code, exception answers by code, clients."""

    def __init__(self, server: ModbusServer) -> None:
        self.server = server

    def collect(self) -> Iterator[Metric]:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        image = self.server.image
        requests = CounterMetricFamily(
            "plcstack_modbus_requests", "Modbus requests by function code", labels=["function"]
        )
        for function, n in sorted(image.requests.items()):
            requests.add_metric([str(function)], float(n))
        yield requests
        exceptions = CounterMetricFamily(
            "plcstack_modbus_exceptions",
            "Modbus exception answers by exception code",
            labels=["code"],
        )
        for code, n in sorted(image.exceptions.items()):
            exceptions.add_metric([f"0x{code:02X}"], float(n))
        yield exceptions
        yield GaugeMetricFamily(
            "plcstack_modbus_clients", "Modbus clients connected", value=float(self.server.clients)
        )
        yield CounterMetricFamily(
            "plcstack_modbus_writes_confirmed",
            "tag writes from Modbus confirmed by the PLC",
            value=float(image.writes_confirmed),
        )
