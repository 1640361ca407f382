"""FETCH/WRITE client: ``fetchwrite://HOST:PORT`` with S5 addresses (``DB10.DW5``, ``MW10``, ...).

URL options (keyword arguments of :func:`plcstack.connect` override them):

``mk=1``              wrap every job in the Tani MK header (spec C.1-C.5)
``db_start=byte``     the CP reads the DB start address as a byte number (VIPA-style, C.6.3)
``write_port=N``      WRITE jobs go over a second connection to port N (CPs configured with a
                      "FETCH passive" and a "WRITE passive" connection on different ports)
``life_ack=SECONDS``  MK keep-alive: send a life ack after that long without sending; a peer
                      that sends nothing at all for ``life_timeout`` (default 3 x interval) is
                      declared dead, its connection closed, and the next request fails with
                      :class:`~plcstack.errors.ConnectionLost` saying so (then reconnects)
``life_timeout=S``    see above
``mk_seq=0``          do not check the MK sequence numbers of answers (for CPs that do not
                      count them); checked by default, as they are the only way to tell a
                      delayed copy of an earlier answer from the current one
``strict=1``          strict MK receive checks (reserved flags, 1460 bytes)
``timeout``, ``connect_timeout``  as for every client

Data are big-endian S5 words. Word reads return 0..65535, byte reads 0..255. Writes accept
-32768..65535 for words and -128..255 for bytes (negative values are two's complement).
"""

from __future__ import annotations

import asyncio
import copy
import logging
import struct
from collections.abc import Hashable, Sequence
from typing import Any, Final, Literal, Self

from plcstack.clients.base import Points, as_points
from plcstack.clients.exchange import RequestClient
from plcstack.clients.options import COMMON, choice, flag, integer, seconds
from plcstack.clients.s5access import S5Access
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.fetchwrite import (
    ClientConnection,
    FetchRequest,
    FetchResponse,
    WriteRequest,
    WriteResponse,
    data_bytes,
    encode_request,
    error_meaning,
)
from plcstack.codecs.mk import LifeAckTimer, MkConnection
from plcstack.diagnose import Failure, fetchwrite_hint
from plcstack.durations import check_seconds
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    ValueEncodeError,
)
from plcstack.s5address import FETCHWRITE_ORG, S5Address, S5Area, S5Unit, parse_s5_address
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Receiver
from plcstack.transports.tcp import TcpTransport
from plcstack.url import PlcUrl
from plcstack.values import pack_ints

__all__ = ["MAX_JOB_BYTES", "FetchWriteClient"]

log = logging.getLogger(__name__)

#: most data bytes one job moves [R]: the CP143 range for a DB (2048 words); the protocol's
#: 16-bit length would allow more, but real CPs refuse it and a poller gains nothing from it
MAX_JOB_BYTES: Final = 4096

DbStart = Literal["word", "byte"]
Response = FetchResponse | WriteResponse

#: a read's cached plan: the FETCH job, data bytes to skip, whether the points are words
_ReadPlan = tuple[FetchRequest, int, bool]
#: a write's cached plan: the point unit and the WRITE header fields (ORG, DBNR, start, length)
_WritePlan = tuple[S5Unit, int, int, int, int]
#: most (address, count) read plans a client keeps (a poller reads a fixed set of tags)
_PLAN_CACHE: Final = 1024


class _Traffic:
    """A receiver that tells the life-ack timer about every chunk, then hands it on."""

    __slots__ = ("receiver", "timer")

    def __init__(self, timer: LifeAckTimer, receiver: Receiver) -> None:
        self.timer = timer
        self.receiver = receiver

    def chunk_received(self, data: bytes) -> None:
        self.timer.received(asyncio.get_running_loop().time())
        self.receiver.chunk_received(data)

    def receive_failed(self, exc: Exception) -> None:
        self.receiver.receive_failed(exc)


class _MkTcpTransport(TcpTransport):
    """TCP that tells a life-ack timer about every byte of traffic, including the life acks
    the client takes between jobs (``take_received``), which the MK codec then consumes."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(host, port)
        self.timer: LifeAckTimer | None = None

    def write(self, data: bytes) -> None:
        super().write(data)
        if self.timer is not None:
            self.timer.sent(asyncio.get_running_loop().time())

    async def read(self, deadline: float | None = None) -> bytes:
        data = await super().read(deadline)
        if self.timer is not None:
            self.timer.received(asyncio.get_running_loop().time())
        return data

    def send_delivering(self, data: bytes, receiver: Receiver, timeout: float) -> None:
        if self.timer is None:
            super().send_delivering(data, receiver, timeout)
        else:
            super().send_delivering(data, _Traffic(self.timer, receiver), timeout)

    def take_received(self) -> list[bytes]:
        chunks = super().take_received()
        if chunks and self.timer is not None:  # life acks taken between jobs are traffic too
            self.timer.received(asyncio.get_running_loop().time())
        return chunks


class FetchWriteClient(S5Access, RequestClient[Response]):
    """Read and write S5 memory through a CP's FETCH/WRITE service (raw TCP or MK header)."""

    OPTIONS = (
        *COMMON,
        flag("mk", False, "wrap every job in the Tani MK header (C.1-C.5)"),
        choice("db_start", "word", ("word", "byte"), "unit of a DB start address (C.6.3)"),
        integer("write_port", None, 1, 65535, "WRITE jobs over a second connection to this port"),
        seconds("life_ack", None, "MK keep-alive interval (needs mk=1)"),
        seconds("life_timeout", None, "peer silence that declares it dead (default 3 x life_ack)"),
        flag("strict", False, "strict MK receive checks"),
        flag("mk_seq", True, "check the MK sequence numbers of answers (C.2)"),
    )

    codec: ClientConnection

    def __init__(
        self,
        name: str,
        host: str,
        port: int,
        *,
        mk: bool = False,
        db_start: DbStart = "word",
        write_port: int | None = None,
        life_ack: float | None = None,
        life_timeout: float | None = None,
        strict: bool = False,
        mk_seq: bool = True,
        timeout: float = 2.0,
        connect_timeout: float = 3.0,
        backoff: Backoff | None = None,
    ) -> None:
        if db_start not in ("word", "byte"):
            raise AddressError(f"db_start must be 'word' or 'byte', not {db_start!r}", plc=name)
        if (life_ack is not None or life_timeout is not None) and not mk:
            raise AddressError("life acks exist only with the MK header: add mk=1", plc=name)
        if life_ack is not None:
            life_ack = check_seconds("life_ack", life_ack, plc=name)
        if life_timeout is not None:
            life_timeout = check_seconds("life_timeout", life_timeout, plc=name)
        if life_ack is not None and life_timeout is None:
            life_timeout = 3 * life_ack  # D.C4
        transport = _MkTcpTransport(host, port) if mk else TcpTransport(host, port)
        super().__init__(
            name, transport, timeout=timeout, connect_timeout=connect_timeout, backoff=backoff
        )
        self.mk = mk
        self.db_start: DbStart = db_start
        self.life_ack = life_ack
        self.life_timeout = life_timeout
        self.strict = strict
        self.mk_seq = mk_seq
        #: times a silent peer was declared dead (life ack timeout)
        self.dead_peers = 0
        self._keeper: asyncio.Task[None] | None = None
        self._pending_error: PlcError | None = None
        self._writer: FetchWriteClient | None = None
        self._read_plans: dict[tuple[str, int], _ReadPlan] = {}
        self._write_plans: dict[tuple[str, int], _WritePlan] = {}
        if write_port is not None:
            self._writer = FetchWriteClient(
                f"{name} [write connection, port {write_port}]",
                host,
                write_port,
                mk=mk,
                db_start=db_start,
                life_ack=life_ack,
                life_timeout=life_timeout,
                strict=strict,
                mk_seq=mk_seq,
                timeout=timeout,
                connect_timeout=connect_timeout,
                backoff=copy.copy(backoff),  # each connection backs off on its own
            )
            self._writer.stats = self.stats

    @classmethod
    def create(cls, url: PlcUrl, options: dict[str, Any]) -> Self:
        assert url.host is not None and url.port is not None
        return cls(url.raw, url.host, url.port, **options)

    def diagnose(self, failure: Failure, reply: bytes) -> str:
        return fetchwrite_hint(failure, reply, mk=self.mk, first=self.first_ever())

    # -- connection life cycle ----------------------------------------------------------------
    def new_codec(self) -> ClientConnection:
        if self.mk:
            return ClientConnection(
                "mk", mk=MkConnection(strict=self.strict, check_seq=self.mk_seq)
            )
        return ClientConnection("raw")

    def connection_made(self) -> None:
        super().connection_made()
        self._stop_keeper()
        if isinstance(self.transport, _MkTcpTransport):
            loop = asyncio.get_running_loop()
            self.transport.timer = LifeAckTimer(self.life_ack, self.life_timeout, loop.time())
            if self.life_ack is not None or self.life_timeout is not None:
                self._keeper = loop.create_task(self._keep_alive(self.transport.timer))

    def connection_dropped(self) -> None:
        self._stop_keeper()

    def _stop_keeper(self) -> None:
        keeper, self._keeper = self._keeper, None
        if keeper is not None and keeper is not asyncio.current_task():
            keeper.cancel()

    async def open(self) -> None:
        await super().open()
        if self._writer is not None:
            try:
                await self._writer.open()
            except BaseException:
                self._stop_keeper()
                self.transport.abort()
                raise

    async def aclose(self) -> None:
        self._stop_keeper()
        try:
            if self._writer is not None:
                await self._writer.aclose()
        finally:
            await super().aclose()

    async def _keep_alive(self, timer: LifeAckTimer) -> None:
        """MK keep-alive, [R] C.3: send life acks when idle; a silent peer is declared dead.

        Runs between jobs only (it takes the single-flight lock), so it never interleaves with a
        job's telegrams; during a job the job's own deadline supervises the peer.
        """
        try:
            await self._keep_alive_loop(timer)
        finally:
            if self._keeper is asyncio.current_task():
                self._keeper = None

    async def _keep_alive_loop(self, timer: LifeAckTimer) -> None:
        loop = asyncio.get_running_loop()
        while True:
            wake = timer.next_wakeup()
            assert wake is not None
            await asyncio.sleep(max(0.0, wake - loop.time()))
            async with self._lock:
                transport = self.transport
                if not transport.is_open or getattr(transport, "timer", None) is not timer:
                    return
                try:
                    await self._consume_idle_input()
                except ConnectionLost:
                    # The peer closed the idle connection (e.g. its own life-ack supervision):
                    # nothing was lost, the next job reconnects as it would without keep-alive.
                    self.drop()
                    return
                except PlcError as exc:
                    self._declare_broken(f"protocol error between jobs: {exc.message}")
                    return
                now = loop.time()
                if timer.dead(now):
                    self.dead_peers += 1
                    self._declare_broken(
                        f"peer dead: nothing received (not even a life ack) for "
                        f"{timer.timeout:g} s; connection closed"
                    )
                    return
                if timer.ack_due(now):
                    transport.write(self.codec.life_ack())

    async def _consume_idle_input(self) -> None:
        """Feed bytes that arrived between jobs (life acks) to the codec without waiting."""
        while True:
            try:
                async with asyncio.timeout(0):
                    data = await self.transport.read()
            except TimeoutError:
                return
            self.codec.receive_data(data)
            if self.codec.next_event() is not NEED_DATA:  # only raises or NEED_DATA when idle
                return  # pragma: no cover

    def _declare_broken(self, message: str) -> None:
        log.warning("%s: %s", self.name, message)
        self.stats.errors += 1
        self._pending_error = ConnectionLost(message, plc=self.name)
        self.drop()

    def take_pending_error(self) -> PlcError | None:
        """The error a broken connection left for the next request (once), or None."""
        pending, self._pending_error = self._pending_error, None
        return pending

    # -- jobs ---------------------------------------------------------------------------------
    async def _job(self, request: FetchRequest | WriteRequest, what: str) -> Response:
        is_write = isinstance(request, WriteRequest)
        client = self._writer if is_write and self._writer is not None else self
        pending = client.take_pending_error()
        if pending is not None:
            raise pending.bind(plc=client.name, request=what)
        response = await client.exchange(request, what, is_write=is_write)
        if response.error:
            client.count_error()
            raise PlcErrorResponse(
                response.error, error_meaning(response.error), plc=client.name, request=what
            )
        return response

    async def read(self, address: str, count: int = 1) -> list[int]:
        what = f"read {address} x{count}"
        plan = (
            self._read_plans.get((address, count))
            if type(address) is str and type(count) is int
            else None
        )
        if plan is None:
            try:
                plan = self._read_plan(address, count)
            except AddressError as exc:
                raise exc.bind(plc=self.name, request=what) from None
        request, skip, words = plan
        response = await self._job(request, what)
        assert isinstance(response, FetchResponse)
        data = response.data
        if words:
            return list(struct.unpack_from(f">{count}H", data, skip))
        return list(data[skip : skip + count])

    def _read_plan(self, address: str, count: int) -> _ReadPlan:
        """Parse and check ``address`` x ``count`` once: the FETCH job, the leading data bytes
        to skip and whether the points are words. Cached per client (the ``db_start`` option
        shapes the job), so a poller's repeated reads skip parsing and checking."""
        addr = parse_s5_address(address)
        self._check_count(addr, count)
        request, skip = self._fetch_for(addr, count)
        plan = (request, skip, addr.unit is S5Unit.WORD)
        if len(self._read_plans) < _PLAN_CACHE:
            self._read_plans[(address, count)] = plan
        return plan

    async def write(self, address: str, values: Points) -> None:
        values = as_points(values, plc=self.name, request=f"write {address}")
        n = len(values)
        what = f"write {address} x{n}"
        plan = self._write_plans.get((address, n)) if type(address) is str else None
        try:
            if plan is None:
                addr = parse_s5_address(address)
                self._check_count(addr, n)
                unit = addr.unit
            else:
                unit = plan[0]
            data = pack_ints(values, ">", "H" if unit is S5Unit.WORD else "B")
            if data is None:
                data = _encode_values(unit, values)
            if plan is None:
                request = self._write_for(addr, data)
                if type(address) is str and len(self._write_plans) < _PLAN_CACHE:
                    # the job's header fields depend only on (address, count): keep them
                    self._write_plans[(address, n)] = (unit, request.org, request.db,
                                                       request.start, request.length)  # fmt: skip
            else:
                _, org, db, start, length = plan
                request = WriteRequest(org, db, start, length, data)
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=what) from None
        await self._job(request, what)

    async def fetch_org(self, org: int, db: int, start: int, length: int) -> bytes:
        """FETCH by raw header fields, for ORG ids S5 notation has no name for (PB, BS, AS, DE,
        QB): ``length`` in the ORG's units (C.6.3); returns the data bytes as sent by the CP."""
        what = f"fetch ORG {org:#04x} DBNR {db} start {start} length {length}"
        try:
            request = FetchRequest(org, db, start, length)
            _check_raw(request)
        except PlcError as exc:
            raise AddressError(exc.message, plc=self.name, request=what) from None
        response = await self._job(request, what)
        return response.data if isinstance(response, FetchResponse) else b""

    async def write_org(self, org: int, db: int, start: int, data: bytes) -> None:
        """WRITE by raw header fields; ``data`` must be whole units of the ORG (C.6.3)."""
        what = f"write ORG {org:#04x} DBNR {db} start {start} {len(data)} bytes"
        try:
            request = WriteRequest.of(org, db, start, bytes(data))
            _check_raw(request)
        except PlcError as exc:
            raise AddressError(exc.message, plc=self.name, request=what) from None
        await self._job(request, what)

    # -- address mapping ----------------------------------------------------------------------
    def _check_count(self, addr: S5Address, count: int) -> None:
        if not isinstance(count, int) or isinstance(count, bool) or count < 1:
            raise AddressError(f"count must be a positive integer, not {count!r}")
        limit = self._limit(addr)
        if count > limit:
            raise AddressError(
                f"{count} points exceed the {limit} one FETCH/WRITE job of {addr} may move"
            )
        last = addr.offset + (count - 1) * addr.step
        if last > 0xFFFF:
            raise AddressError(f"{count} points from {addr} run past offset 65535")

    @staticmethod
    def _limit(addr: S5Address) -> int:
        if addr.area.is_block and addr.unit is S5Unit.BYTE:
            return MAX_JOB_BYTES - 2  # an odd start needs one extra word
        return MAX_JOB_BYTES // addr.unit.size

    def _db_start(self, dw: int) -> int:
        start = 2 * dw if self.db_start == "byte" else dw
        if start > 0xFFFF:
            raise AddressError(f"DW{dw} cannot be addressed with a byte start address")
        return start

    def _fetch_for(self, addr: S5Address, count: int) -> tuple[FetchRequest, int]:
        """The FETCH job for ``count`` points and how many leading data bytes to skip."""
        org = FETCHWRITE_ORG[addr.area]
        db = addr.db or 0
        if addr.area.is_block:
            first = addr.byte_offset // 2
            last = (addr.byte_offset + addr.byte_length(count) - 1) // 2
            skip = addr.byte_offset % 2
            return FetchRequest(org, db, self._db_start(first), last - first + 1), skip
        if addr.area in (S5Area.TIMERS, S5Area.COUNTERS):
            return FetchRequest(org, 0, addr.offset, count), 0
        return FetchRequest(org, 0, addr.offset, addr.byte_length(count)), 0

    def _write_for(self, addr: S5Address, data: bytes) -> WriteRequest:
        org = FETCHWRITE_ORG[addr.area]
        if addr.area.is_block:
            if addr.byte_offset % 2 or len(data) % 2:
                raise AddressError(
                    f"FETCH/WRITE writes {addr.area.value} data in whole words; {addr} with "
                    f"{len(data)} byte(s) does not cover whole data words (write DWs instead)"
                )
            return WriteRequest(
                org, addr.db or 0, self._db_start(addr.byte_offset // 2), len(data) // 2, data
            )
        if addr.area in (S5Area.TIMERS, S5Area.COUNTERS):
            return WriteRequest(org, 0, addr.offset, len(data) // 2, data)
        return WriteRequest(org, 0, addr.offset, len(data), data)

    # -- poller hooks -------------------------------------------------------------------------
    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        try:
            addr = parse_s5_address(address)
            self._check_count(addr, count)
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=f"locate {address} x{count}") from None
        if addr.step == 2:
            # M/E/A words advance by 2 bytes per point; MW10 and MW11 are different grids.
            return (addr.area, addr.db, addr.unit, addr.offset % 2), addr.offset // 2
        return (addr.area, addr.db, addr.unit, 0), addr.offset

    def address_at(self, area: Hashable, index: int) -> str:
        s5area, db, unit, parity = _area_key(area)
        step = S5Address(s5area, unit, 0, db).step
        return S5Address(s5area, unit, index * step + parity, db).to_str()

    def max_points(self, area: Hashable) -> int:
        s5area, db, unit, _ = _area_key(area)
        return self._limit(S5Address(s5area, unit, 0, db))

    def point_bits(self, area: Hashable) -> int:
        """Width of one point of ``area`` for the poller: 16 for words, 8 for bytes."""
        return 8 * _area_key(area)[2].size


def _check_raw(request: FetchRequest | WriteRequest) -> None:
    if request.length < 1 or data_bytes(request.org, request.length) > MAX_JOB_BYTES:
        raise AddressError(f"length must be 1..{MAX_JOB_BYTES} bytes worth of units")
    encode_request(request)  # field ranges


def _area_key(area: Hashable) -> tuple[S5Area, int | None, S5Unit, int]:
    """Check and unpack an area key made by :meth:`FetchWriteClient.locate`."""
    if (
        isinstance(area, tuple)
        and len(area) == 4
        and isinstance(area[0], S5Area)
        and (area[1] is None or isinstance(area[1], int))
        and isinstance(area[2], S5Unit)
        and area[3] in (0, 1)
    ):
        return area[0], area[1], area[2], area[3]
    raise AddressError(f"{area!r} is not a FETCH/WRITE area key (use locate())")


def _encode_values(unit: S5Unit, values: Sequence[int] | Sequence[bool]) -> bytes:
    if isinstance(values, str | bytes) or not isinstance(values, Sequence):
        raise AddressError(f"values must be a sequence of integers, not {type(values).__name__}")
    lo, hi = (-0x8000, 0xFFFF) if unit is S5Unit.WORD else (-0x80, 0xFF)
    out = bytearray()
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueEncodeError(
                f"value {value!r} ({type(value).__name__}) is not an integer "
                "(S5 has no bit writes here)"
            )
        if not lo <= value <= hi:
            raise AddressError(f"value {value} is outside {lo}..{hi}")
        out += (value & (0xFFFF if unit is S5Unit.WORD else 0xFF)).to_bytes(unit.size, "big")
    return bytes(out)
