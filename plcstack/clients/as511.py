"""AS511 client (PG side) for S5-90U...115U CPUs over a serial line or a serial device server.

``as511:///dev/ttyS0?baud=9600`` (8E1 by default; ``parity=``, ``stopbits=``) or
``as511+tcp://HOST:PORT`` (a serial device server; ``baud=`` is the line rate behind it and only
stretches deadlines for long frames). Further options: ``char_timeout`` (0.5 s, B5.7),
``response_timeout`` (defaults to ``char_timeout``; D.B6), ``cache`` (block address cache, on),
``strict`` (check the 5 leading zero bytes of read answers, off; D.B2), ``timeout`` (upper bound of
one transaction on top of its line time) and ``connect_timeout``.

AS511 talks byte by byte, so this client drives the :class:`~plcstack.codecs.as511.PGConnection`
machine itself instead of ``RequestClient.exchange``; it keeps the base's single-flight lock,
reconnect/backoff and error binding. Decisions:

* Block addresses (DW0 from B_INFO) are cached per block. A read with a cached address also reads
  the block's 10-byte header in the same transaction and checks its signature (``70 70``, type,
  number, length); a mismatch, a NAK or an answer of the wrong length drops the entry and the read
  is repeated once after a fresh B_INFO. A *write* always asks B_INFO first, as libnodave does:
  writing to a stale address would corrupt whatever block moved there.
* After a DLE NAK or any abort the next STX waits until the line was silent for 500 ms (B5.1,
  B5.5); bytes arriving meanwhile are discarded, so a late answer is never taken for the next one.
  On a serial line that rule is the resynchronisation and the port stays open; over TCP a
  timeout or malformed answer also closes the connection (a device server may have gone away).
* Reads are split into transactions of at most 512 bytes, writes likewise (B.7.3/B.7.4). A split
  write that fails part-way says how many bytes were written.
* I/Q/M/T/C use the base addresses of function 18h (read once per connection). Their sizes are
  those of the S5-115U layout (I/Q 128 bytes, M 256 bytes, T/C 128 words) [R]; the system
  parameters give the bases but no sizes.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Hashable, Sequence
from typing import Any, Self

from plcstack.clients.base import (
    DEFAULT_CONNECT_TIMEOUT,
    DEFAULT_TIMEOUT,
    Client,
    Points,
    as_points,
)
from plcstack.clients.options import COMMON, Option, choice, flag, integer, seconds
from plcstack.clients.s5access import S5Access
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import (
    DEFAULT_CHAR_TIMEOUT,
    MAX_READ_BYTES,
    MAX_WRITE_BYTES,
    BlockInfo,
    Job,
    PGConnection,
    PGState,
    Response,
    SystemAddresses,
    Timeout,
    b_info_job,
    block_list_job,
    header_matches,
    operating_mode_job,
    parse_b_info,
    parse_read,
    parse_system_parameters,
    read_job,
    run_job,
    stop_job,
    system_parameters_job,
    write_job,
)
from plcstack.diagnose import Failure, as511_hint
from plcstack.durations import check_seconds
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
    ValueEncodeError,
)
from plcstack.s5address import S5Address, S5Area, S5Unit, parse_s5_address
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.transports.serial import SerialTransport
from plcstack.transports.tcp import TcpTransport
from plcstack.url import PlcUrl
from plcstack.values import pack_ints

__all__ = ["AREA_BYTES", "BLOCK_TYPES", "AS511Client"]

#: AS511 block type codes (B.6) by name
BLOCK_TYPES: dict[str, int] = {
    "DB": 0x01,
    "SB": 0x02,
    "PB": 0x04,
    "FX": 0x05,
    "FB": 0x08,
    "DX": 0x0C,
    "OB": 0x10,
}

#: bytes per area outside blocks (S5-115U layout) [R]
AREA_BYTES: dict[S5Area, int] = {
    S5Area.INPUTS: 128,
    S5Area.OUTPUTS: 128,
    S5Area.FLAGS: 256,
    S5Area.TIMERS: 256,
    S5Area.COUNTERS: 256,
}

_SYSPAR_FIELD = {
    S5Area.INPUTS: "inputs",
    S5Area.OUTPUTS: "outputs",
    S5Area.FLAGS: "flags",
    S5Area.TIMERS: "timers",
    S5Area.COUNTERS: "counters",
}

_WAITING_FOR = {
    PGState.W_ACK1: "DLE ACK after STX (is the PLC connected, powered and on this port?)",
    PGState.W_STX1: "STX after the function code",
    PGState.W_ACCEPT: "the accept frame",
    PGState.W_ACK2: "DLE ACK after the parameters",
    PGState.W_STX2: "the data frame",
    PGState.RX_DATA: "the rest of the data frame",
    PGState.W_STX3: "the terminate frame",
    PGState.W_END: "the terminate frame",
}

_NAK_MEANING = {
    "ready": "the PLC is busy and refused to start a transaction (DLE NAK after STX)",
    "function": "the PLC does not support function {fn:02X}h (DLE NAK instead of STX)",
    "params": "the PLC refused the operation (DLE NAK after the parameters)",
}

#: header bytes prepended to a cached block read for the signature check, if the gap is small
_MAX_SIGNATURE_GAP = 64
#: most (address, count) word reads whose checks :meth:`AS511Client.read` keeps
_MAX_PLANS = 4096
_BITS_PER_BYTE = 11  # 8E1


def _stopbits(value: object) -> object:
    if isinstance(value, bool) or not isinstance(value, int | float) or value not in (1, 1.5, 2):
        raise ValueError("not 1, 1.5 or 2")
    return float(value)


def _after_signature(head: bytes, info: BlockInfo, offset: int) -> bytes:
    """What follows the block header (and ``offset`` bytes) in a read that began at the header;
    :class:`_BlockMoved` when the header is not the cached block's any more."""
    header = head[:10]
    if not header_matches(header, info.block_type, info.number) or header != info.header:
        raise _BlockMoved
    return head[10 + offset :]


class _BlockMoved(Exception):
    """The header read with a cached address does not match: the block moved."""


def _block_type(block_type: int | str) -> tuple[int, str]:
    if isinstance(block_type, str):
        name = block_type.upper()
        if name not in BLOCK_TYPES:
            raise AddressError(
                f"unknown block type {block_type!r}; known: {', '.join(BLOCK_TYPES)}"
            )
        return BLOCK_TYPES[name], name
    for name, code in BLOCK_TYPES.items():
        if code == block_type:
            return code, name
    raise AddressError(f"unknown block type code {block_type:#04x}")


def _as_user_request(exc: PlcError, what: str) -> PlcError:
    """Name the request as the caller wrote it (``read MW100 x1``), keeping the AS511 step that
    failed in brackets: logs are searched for the address the user configured, which the
    transaction-level wording (``read M bytes 100..101``) did not contain."""
    if exc.request is None or exc.request.startswith(what):
        exc.request = what
    else:
        exc.request = f"{what} ({exc.request})"
    return exc


class AS511Client(S5Access, Client):
    """Read and write an S5 CPU through its programming port (spec part B)."""

    OPTIONS = (
        *COMMON,
        integer("baud", 9600, 50, 4_000_000, "line rate (behind a device server: for deadlines)"),
        seconds("char_timeout", DEFAULT_CHAR_TIMEOUT, "silence that ends a frame (B5.7)"),
        seconds("response_timeout", None, "wait for an answer; default char_timeout (D.B6)"),
        seconds("nak_backoff", 0.5, "pause after a DLE NAK before the next STX (B5.1)"),
        flag("cache", True, "cache block addresses from B_INFO"),
        flag("strict", False, "check the 5 leading zero bytes of read answers (D.B2)"),
    )
    #: the cached-address word read in one await (see :meth:`read`); tests switch it off to
    #: compare it with the general path
    fast_paths = True
    #: a serial line adds its character format
    SERIAL_OPTIONS = (
        *OPTIONS,
        choice("parity", "E", ("N", "E", "O"), "parity (8E1 by default)"),
        Option("stopbits", 1.0, float, _stopbits, "stop bits: 1, 1.5 or 2"),
    )

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        char_timeout: float = DEFAULT_CHAR_TIMEOUT,
        response_timeout: float | None = None,
        nak_backoff: float = 0.5,
        line_byte_time: float | None = None,
        cache: bool = True,
        strict: bool = False,
        timeout: float = DEFAULT_TIMEOUT,
        connect_timeout: float = DEFAULT_CONNECT_TIMEOUT,
        backoff: Backoff | None = None,
    ) -> None:
        super().__init__(
            name, transport, timeout=timeout, connect_timeout=connect_timeout, backoff=backoff
        )
        char_timeout = check_seconds("char_timeout", char_timeout, plc=name)
        if response_timeout is not None:
            response_timeout = check_seconds("response_timeout", response_timeout, plc=name)
        if line_byte_time is None:
            line_byte_time = (
                transport.byte_time
                if isinstance(transport, SerialTransport)
                else _BITS_PER_BYTE / 9600
            )
        self.line_byte_time = line_byte_time
        self.pg = PGConnection(
            char_timeout=char_timeout,
            response_timeout=response_timeout,
            backoff=nak_backoff,
            tx_byte_time=line_byte_time,
        )
        self.cache_enabled = cache
        self.strict = strict
        self.block_cache: dict[tuple[int, int], BlockInfo] = {}
        #: (address, count) -> (block type code, number, byte offset, byte length, "what" text,
        #: word layout) of DB/DX word reads already parsed and checked, whose header and data
        #: fit one transaction: a poller reads the same few addresses every scan (see read)
        self._block_word_reads: dict[
            tuple[str, int], tuple[int, int, int, int, str, struct.Struct]
        ] = {}
        #: (start, length) -> the 04h job of that span, for the reads above
        self._read_jobs: dict[tuple[int, int], Job] = {}
        self._sysparams: SystemAddresses | None = None
        # A serial line resynchronises by the 500 ms silence rule; TCP may be half-open.
        self._drop_on_error = not isinstance(transport, SerialTransport)

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def options_for(cls, url: PlcUrl) -> tuple[Option, ...]:
        return cls.SERIAL_OPTIONS if url.transport == "serial" else cls.OPTIONS

    @classmethod
    def create(cls, url: PlcUrl, options: dict[str, Any]) -> Self:
        opts = dict(options)
        baud = opts.pop("baud")
        transport: Transport
        if url.transport == "serial":
            assert url.path is not None
            transport = SerialTransport(
                url.path, baudrate=baud, parity=opts.pop("parity"), stopbits=opts.pop("stopbits")
            )
        else:
            assert url.host is not None and url.port is not None
            transport = TcpTransport(url.host, url.port)
            opts["line_byte_time"] = _BITS_PER_BYTE / baud
        return cls(url.raw, transport, **opts)

    def connection_made(self) -> None:
        self.pg.reset(asyncio.get_running_loop().time())
        self._sysparams = None  # a re-plugged cable may lead to another CPU

    # -- one transaction --------------------------------------------------------------------
    async def transact(
        self, job: Job, what: str, *, is_write: bool = False, nak_meaning: str | None = None
    ) -> bytes:
        """Run one AS511 transaction and return its unstuffed data frame (b"" without one).

        Failures go through the clients' one failure policy (:meth:`Client.request_failed`);
        what a failed write had reached is the codec's :attr:`PGConnection.delivery`.
        """
        async with self._lock:
            await self._ensure_open(what)
            self.stats.requests += 1
            # every chunk received during this transaction, kept only for the failure hint
            chunks: list[bytes] = []
            pg = self.pg
            try:
                # The dialogue runs in this frame (no ``await self._run(...)``): every answer of
                # the AS511 dialogue resumes the whole chain of awaiting coroutines, so one
                # level less is paid 7 times per transaction.
                loop = asyncio.get_running_loop()
                out_bytes = 20 + 2 * len(job.params)
                in_bytes = 20 + 2 * (job.response_length or 64)
                cap = self.timeout + (out_bytes + in_bytes) * self.line_byte_time + pg.backoff
                # The whole transaction's bound, checked in the loop rather than by an
                # ``asyncio.timeout`` context (a timer and a context per transaction; AS511
                # runs 2-3 transactions per read): every wait is capped by it, and a peer that
                # keeps sending bytes meets the check after each chunk.
                give_up = loop.time() + cap
                transport = self.transport
                try:
                    # B5.1/B5.5: after an abort, wait for 500 ms of silence before the next STX.
                    while (wait := pg.ready_at - loop.time()) > 0:
                        try:
                            data = await transport.read(min(loop.time() + wait, give_up))
                        except TimeoutError:
                            if loop.time() >= give_up:
                                raise
                            continue
                        pg.receive_data(data, loop.time())
                        if loop.time() >= give_up:
                            raise TimeoutError
                    pg.submit(job, max(loop.time(), pg.ready_at))
                    transport.write(pg.data_to_send())
                    while (event := pg.next_event()) is NEED_DATA:
                        deadline = pg.deadline
                        capped = deadline is None or deadline > give_up
                        try:
                            data = await transport.read(give_up if capped else deadline)
                        except TimeoutError:
                            if capped:
                                raise
                            pg.timer(max(loop.time(), deadline or 0.0))
                        else:
                            chunks.append(data)
                            now = loop.time()
                            if now >= give_up:
                                raise TimeoutError from None
                            pg.receive_data(data, now)
                        out = pg.data_to_send()
                        if out:
                            transport.write(out)
                except TimeoutError:
                    state = pg.state
                    pg.reset(loop.time())
                    raise PlcTimeout(
                        f"no complete answer within {cap:.2f} s "
                        f"(AS511 transaction stuck in {state.value})"
                    ) from None
                except (ConnectionLost, RemoteProtocolError):
                    pg.reset(loop.time())
                    raise
            except asyncio.CancelledError:
                # The caller gave up mid-transaction: the PG must start over (B5.5 silence on a
                # line, a new connection on TCP), or every later request finds the transaction
                # "already in progress".
                pg.reset(asyncio.get_running_loop().time())
                if self._drop_on_error:
                    self._drop()
                raise
            except (PlcTimeout, ConnectionLost, RemoteProtocolError) as exc:
                failure: Failure = (
                    "timeout"
                    if isinstance(exc, PlcTimeout)
                    else "closed"
                    if isinstance(exc, ConnectionLost)
                    else "malformed"
                )
                # a serial line resynchronises from a timeout by silence (B5.5)
                drop = self._drop_on_error or failure != "timeout"
                raise self.request_failed(
                    exc,
                    failure,
                    b"".join(chunks),
                    what,
                    is_write=is_write,
                    sent=True,
                    drop=drop,
                    outcome=pg.delivery.value,
                ) from None
            if isinstance(event, Timeout):
                state = PGState(event.state)
                executing = state in (PGState.W_ACK2, PGState.W_STX2) or (
                    state is PGState.W_STX3 and not job.has_response
                )
                wait = pg.response_timeout if executing else pg.char_timeout
                error = PlcTimeout(
                    f"no complete answer within {wait:g} s (waiting for {_WAITING_FOR[state]})"
                )
                raise self.request_failed(
                    error,
                    "timeout",
                    b"".join(chunks),
                    what,
                    is_write=is_write,
                    sent=True,
                    drop=self._drop_on_error,
                    outcome=pg.delivery.value,
                )
            if self._unproven:
                self._answered()
        if isinstance(event, Response):
            return event.data
        self.stats.errors += 1
        meaning = _NAK_MEANING[event.step].format(fn=event.fn)
        if event.step == "params" and nak_meaning:
            meaning = nak_meaning
        raise PlcErrorResponse(0x15, meaning, plc=self.name, request=what, code_text="DLE NAK")

    def diagnose(self, failure: Failure, reply: bytes) -> str:
        serial = isinstance(self.transport, SerialTransport)
        return as511_hint(failure, reply, serial=serial, first=self.first_on_connection())

    # -- functions --------------------------------------------------------------------------
    async def read_system_parameters(self, *, refresh: bool = False) -> SystemAddresses:
        """Function 18h: base addresses of I/Q/M/T/C and system data (cached per connection)."""
        if self._sysparams is None or refresh:
            data = await self.transact(system_parameters_job(), "read system parameters")
            try:
                self._sysparams = parse_system_parameters(data)
            except RemoteProtocolError as exc:
                self.stats.errors += 1
                raise exc.bind(plc=self.name, request="read system parameters") from None
        return self._sysparams

    async def block_info(self, block_type: int | str, number: int) -> BlockInfo:
        """Function 1Ah (B_INFO): DW0 address and length of a block; refreshes the cache."""
        code, name = _block_type(block_type)
        if not 1 <= number <= 255:
            raise AddressError(f"block number {number} is outside 1..255", plc=self.name)
        what = f"B_INFO {name}{number}"
        missing = f"{name}{number} does not exist in the PLC (B_INFO answered DLE NAK)"
        self.block_cache.pop((code, number), None)
        data = await self.transact(b_info_job(code, number), what, nak_meaning=missing)
        info = parse_b_info(data, code, number)
        if info is None:  # [R] D.B3: a failed signature check means "block not found" too
            self.stats.errors += 1
            raise PlcErrorResponse(
                0x15,
                f"{name}{number} is not usable: the block header failed the signature check "
                f"(answer {data.hex(' ')})",
                plc=self.name,
                request=what,
                code_text="bad block header",
            )
        if self.cache_enabled:
            self.block_cache[(code, number)] = info
        return info

    def invalidate(self, block_type: int | str | None = None, number: int | None = None) -> None:
        """Forget cached block addresses (all, or one block)."""
        if block_type is None:
            self.block_cache.clear()
            return
        code, _ = _block_type(block_type)
        if number is None:
            for key in [k for k in self.block_cache if k[0] == code]:
                del self.block_cache[key]
        else:
            self.block_cache.pop((code, number), None)

    async def read_absolute(self, address: int, length: int, what: str | None = None) -> bytes:
        """Function 04h over ``address .. address+length-1``, split into 512-byte transactions."""
        if length < 1 or address < 0 or address + length > 0x10000:
            raise AddressError(
                f"absolute range {address:#06x}+{length} is outside 0..FFFFh", plc=self.name
            )
        what = what or f"read {length} bytes at {address:04X}h"
        out = bytearray()
        while len(out) < length:
            start = address + len(out)
            n = min(MAX_READ_BYTES, length - len(out))
            out += await self._read_chunk(start, n, what)
        return bytes(out)

    async def _read_chunk(self, start: int, n: int, what: str) -> bytes:
        return self._read_answer(await self.transact(read_job(start, n), what), n, what)

    def _read_answer(self, data: bytes, n: int, what: str) -> bytes:
        try:
            return parse_read(data, n, strict=self.strict)
        except RemoteProtocolError as exc:
            self.stats.errors += 1
            raise exc.bind(plc=self.name, request=what) from None

    async def write_absolute(self, address: int, data: bytes, what: str | None = None) -> None:
        """Function 03h at ``address``, split into 512-byte transactions."""
        data = bytes(data)
        if not data or address < 0 or address + len(data) > 0x10000:
            raise AddressError(
                f"absolute range {address:#06x}+{len(data)} is outside 0..FFFFh", plc=self.name
            )
        what = what or f"write {len(data)} bytes at {address:04X}h"
        done = 0
        while done < len(data):
            chunk = data[done : done + MAX_WRITE_BYTES]
            try:
                await self.transact(
                    write_job(address + done, chunk),
                    what,
                    is_write=True,
                    nak_meaning="the PLC refused the write (DLE NAK after the data): "
                    "address outside memory or protected",
                )
            except PlcError as exc:
                if done:
                    exc.message += f" (the first {done} of {len(data)} bytes were written)"
                raise
            done += len(chunk)

    # -- blocks (DB, DX) --------------------------------------------------------------------
    async def read_block_bytes(
        self, block_type: int | str, number: int, offset: int, length: int
    ) -> bytes:
        """``length`` bytes from byte ``offset`` of a block's body (DW0 = offset 0)."""
        code, name = _block_type(block_type)
        what = f"read {name}{number} bytes {offset}..{offset + length - 1}"
        if length < 1 or offset < 0:
            raise AddressError(f"{what}: empty or negative range", plc=self.name)
        for attempt in range(2):
            cached = self.block_cache.get((code, number)) if self.cache_enabled else None
            info = cached or await self.block_info(code, number)
            if cached is not None and offset + length > info.data_bytes:
                self.block_cache.pop((code, number), None)  # maybe re-created longer: ask again
                continue
            self._check_span(info, name, offset, length, what)
            try:
                if cached is not None and offset <= _MAX_SIGNATURE_GAP:
                    return await self._read_verified(info, offset, length, what)
                return await self.read_absolute(info.dw0 + offset, length, what)
            except _BlockMoved:
                self.block_cache.pop((code, number), None)
                if attempt:
                    raise RemoteProtocolError(
                        f"{name}{number} keeps moving while it is read", plc=self.name
                    ) from None
            except (PlcErrorResponse, RemoteProtocolError):
                self.block_cache.pop((code, number), None)  # any sign that the block moved
                if cached is None or attempt:
                    raise
        raise AssertionError("unreachable")  # pragma: no cover

    async def _read_verified(self, info: BlockInfo, offset: int, length: int, what: str) -> bytes:
        """Read with a cached address, the block header in the first transaction (signature)."""
        first = min(length, MAX_READ_BYTES - 10 - offset)
        head = await self._read_chunk(info.header_address, 10 + offset + first, what)
        out = bytearray(_after_signature(head, info, offset))
        if len(out) < length:
            out += await self.read_absolute(info.dw0 + offset + len(out), length - len(out), what)
        return bytes(out)

    @staticmethod
    def _check_span(info: BlockInfo, name: str, offset: int, length: int, what: str) -> None:
        # [R] B.7.3: the wire has no range check; refuse reads/writes beyond the block's data
        if offset + length > info.data_bytes:
            raise AddressError(
                f"{what}: {name}{info.number} has {info.data_bytes // 2} data words "
                f"({info.data_bytes} bytes)"
            )

    async def write_block_bytes(
        self, block_type: int | str, number: int, offset: int, data: bytes
    ) -> None:
        """Write bytes into a block's body; B_INFO first, every time (see module docstring)."""
        code, name = _block_type(block_type)
        what = f"write {name}{number} bytes {offset}..{offset + len(data) - 1}"
        if not data or offset < 0:
            raise AddressError(f"{what}: empty or negative range", plc=self.name)
        info = await self.block_info(code, number)
        self._check_span(info, name, offset, len(data), what)
        try:
            await self.write_absolute(info.dw0 + offset, data, what)
        except PlcErrorResponse:
            self.block_cache.pop((code, number), None)
            raise

    async def read_db(self, number: int, dw: int, count: int, *, dx: bool = False) -> list[int]:
        """``count`` data words from DW ``dw`` of DB (or DX) ``number``."""
        if count < 1 or dw < 0:
            raise AddressError(f"count {count} / DW{dw} out of range", plc=self.name)
        raw = await self.read_block_bytes("DX" if dx else "DB", number, 2 * dw, 2 * count)
        return list(struct.unpack(f">{count}H", raw))

    async def write_db(
        self, number: int, dw: int, words: Sequence[int], *, dx: bool = False
    ) -> None:
        """Write data words from DW ``dw`` of DB (or DX) ``number``; confirmed by the PLC."""
        await self.write_block_bytes("DX" if dx else "DB", number, 2 * dw, _pack_words(words))

    async def read_dx(self, number: int, dw: int, count: int) -> list[int]:
        return await self.read_db(number, dw, count, dx=True)

    async def write_dx(self, number: int, dw: int, words: Sequence[int]) -> None:
        await self.write_db(number, dw, words, dx=True)

    # -- areas ------------------------------------------------------------------------------
    async def _area_address(self, area: S5Area, offset: int, length: int, what: str) -> int:
        size = AREA_BYTES[area]
        if offset < 0 or length < 1 or offset + length > size:
            raise AddressError(
                f"{what}: area {area.value} has {size} bytes; {offset}+{length} is outside it",
                plc=self.name,
            )
        params = await self.read_system_parameters()
        base: int = getattr(params, _SYSPAR_FIELD[area])
        return base + offset

    async def read_bytes(self, area: S5Area | str, offset: int, count: int) -> bytes:
        """Bytes of I/Q/M/T/C (T/C: 2 bytes per timer/counter) from byte ``offset``."""
        area = _area(area)
        what = f"read {area.value} bytes {offset}..{offset + count - 1}"
        address = await self._area_address(area, offset, count, what)
        return await self.read_absolute(address, count, what)

    async def write_bytes(self, area: S5Area | str, offset: int, data: bytes) -> None:
        area = _area(area)
        what = f"write {area.value} bytes {offset}..{offset + len(data) - 1}"
        address = await self._area_address(area, offset, len(data), what)
        await self.write_absolute(address, data, what)

    async def read_block_list(self, block_type: int | str) -> dict[int, int]:
        """Function 1Bh: ``{block number: address}`` of the blocks of one type (B.7.6).

        The meaning of the addresses is not verified on real CPUs (B.7.6); the simulator returns
        the DW0 address that B_INFO would return.
        """
        code, name = _block_type(block_type)
        what = f"read the {name} block list"
        data = await self.transact(block_list_job(code), what)
        if not data or data[0] != 0 or len(data) % 2 != 1:
            self.stats.errors += 1
            raise RemoteProtocolError(
                f"block list answer of {len(data)} bytes is not 00 + words",
                plc=self.name,
                request=what,
            )
        words = struct.unpack(f">{len(data) // 2}H", data[1:])
        return {number: address for number, address in enumerate(words) if address}

    async def change_operating_mode(self, mode: int) -> int | None:
        """Function 1Eh of 135U/155U CPUs: 0 stop, 1 restart, 2 warm restart (B.7.5).

        Returns the byte the CPU answers for modes 1 and 2 (25h/26h), ``None`` for stop.
        """
        if mode not in (0, 1, 2):
            raise AddressError(f"operating mode {mode} is not 0, 1 or 2", plc=self.name)
        data = await self.transact(
            operating_mode_job(mode), f"change operating mode to {mode}", is_write=True
        )
        return data[0] if data else None

    async def stop(self) -> None:
        """Put a small CPU into STOP (B.7.5: 88 04 at system data + 0Ch)."""
        params = await self.read_system_parameters()
        await self.transact(stop_job(params.system_data), "stop the PLC", is_write=True)

    async def start(self) -> None:
        """Restart a small CPU (B.7.5: 68 00 at system data + 0Ch)."""
        params = await self.read_system_parameters()
        await self.transact(run_job(params.system_data), "start the PLC", is_write=True)

    # -- the generic API --------------------------------------------------------------------
    def _parse(self, address: str, count: int) -> S5Address:
        try:
            addr = parse_s5_address(address)
        except AddressError as exc:
            raise exc.bind(plc=self.name) from None
        if not isinstance(count, int) or isinstance(count, bool) or count < 1:
            raise AddressError(f"count {count!r} must be a positive integer", plc=self.name)
        return addr

    async def read(self, address: str, count: int = 1) -> list[int]:
        """Read in S5 notation: words (DBn.DWk, MW, IW, QW, T, C) or bytes (MB, IB, DL/DR)."""
        try:
            # exact int: 2.0 or True would find the plan of 2 or 1 (equal keys) and skip _parse
            fast = self.fast_paths and type(count) is int
            plan = self._block_word_reads.get((address, count)) if fast else None
            if plan is not None:
                # The polling hot path: a DB/DX word read already checked, whose block address
                # is cached and whose header + data fit one transaction. One await (the
                # transaction) instead of five nested coroutines that each resume on every
                # answer of the AS511 dialogue; the wire work and every check are those of
                # read_block_bytes -> _read_verified. Anything else, including every failure
                # that makes the general path drop the cached address and ask B_INFO again,
                # continues on the general path from exactly that point.
                code, number, offset, length, what, words = plan
                key = (code, number)
                info = self.block_cache.get(key) if self.cache_enabled else None
                if info is not None and offset + length <= info.data_bytes:
                    span = (info.header_address, 10 + offset + length)
                    job = self._read_jobs.get(span)
                    if job is None:
                        job = read_job(*span)  # Job is frozen: one per span serves every read
                        if len(self._read_jobs) < _MAX_PLANS:
                            self._read_jobs[span] = job
                    try:
                        data = await self.transact(job, what)
                        head = self._read_answer(data, 10 + offset + length, what)
                        return list(words.unpack(_after_signature(head, info, offset)))
                    except (_BlockMoved, PlcErrorResponse, RemoteProtocolError):
                        # the general path's first attempt failed the same way: it drops the
                        # address and asks B_INFO again, which _read now does
                        self.block_cache.pop(key, None)
            return await self._read(address, count)
        except PlcError as exc:
            raise _as_user_request(exc, f"read {address} x{count}") from None

    async def _read(self, address: str, count: int) -> list[int]:
        addr = self._parse(address, count)
        nbytes = addr.byte_length(count)
        if (
            addr.area.is_block
            and addr.unit is S5Unit.WORD
            and addr.byte_offset <= _MAX_SIGNATURE_GAP
            and 10 + addr.byte_offset + nbytes <= MAX_READ_BYTES
            and len(self._block_word_reads) < _MAX_PLANS
        ):
            code, name = _block_type(addr.area.value)
            number, offset = addr.db or 0, addr.byte_offset
            what = f"read {name}{number} bytes {offset}..{offset + nbytes - 1}"
            words = struct.Struct(f">{count}H")
            self._block_word_reads[(address, count)] = (code, number, offset, nbytes, what, words)
        if addr.area.is_block:
            raw = await self.read_block_bytes(
                addr.area.value, addr.db or 0, addr.byte_offset, nbytes
            )
        else:
            raw = await self.read_bytes(addr.area, addr.byte_offset, nbytes)
        if addr.unit is S5Unit.WORD:
            return list(struct.unpack(f">{count}H", raw))
        return list(raw)

    async def write(self, address: str, values: Points) -> None:
        """Write in S5 notation; returns once the PLC acknowledged every byte."""
        values = as_points(values, plc=self.name, request=f"write {address}")
        try:
            await self._write(address, values)
        except PlcError as exc:
            raise _as_user_request(exc, f"write {address} x{len(values)}") from None

    async def _write(self, address: str, values: Sequence[int] | Sequence[bool]) -> None:
        addr = self._parse(address, max(1, len(values)))
        if not values:
            raise AddressError("no values to write", plc=self.name, request=f"write {address}")
        try:
            raw = (
                _pack_words(values)
                if addr.unit is S5Unit.WORD
                else bytes(_check_byte(v) for v in values)
            )
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=f"write {address}") from None
        if addr.area.is_block:
            await self.write_block_bytes(addr.area.value, addr.db or 0, addr.byte_offset, raw)
        else:
            await self.write_bytes(addr.area, addr.byte_offset, raw)

    # -- poller hooks -----------------------------------------------------------------------
    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        addr = self._parse(address, count)
        # M/E/A words step by 2 bytes (MW10, MW12, ...): odd and even starts are different grids.
        parity = addr.offset % addr.step
        area = (addr.area.value, addr.db, addr.unit.name, parity)
        index = addr.offset // addr.step
        if addr.byte_offset + addr.byte_length(count) > self._area_limit(addr):
            raise AddressError(f"{address} x{count} is outside its area", plc=self.name)
        return area, index

    def address_at(self, area: Hashable, index: int) -> str:
        letter, db, unit_name, parity = _split_area(area)
        unit = S5Unit[unit_name]
        s5area = S5Area(letter)
        words_by_byte = (S5Area.FLAGS, S5Area.INPUTS, S5Area.OUTPUTS)
        step = 2 if unit is S5Unit.WORD and s5area in words_by_byte else 1
        return S5Address(s5area, unit, index * step + parity, db).to_str()

    def max_points(self, area: Hashable) -> int:
        letter, _, unit_name, _ = _split_area(area)
        per_point = S5Unit[unit_name].size
        # a cached block read carries the 10-byte header in its first transaction
        limit = MAX_READ_BYTES - 10 if letter in ("DB", "DX") else MAX_READ_BYTES
        return limit // per_point

    def point_bits(self, area: Hashable) -> int:
        """Width of one point of ``area`` for the poller: 16 for words, 8 for bytes."""
        return 8 * S5Unit[_split_area(area)[2]].size

    @staticmethod
    def _area_limit(addr: S5Address) -> int:
        return 0x10000 if addr.area.is_block else AREA_BYTES[addr.area]


def _split_area(area: Hashable) -> tuple[str, int | None, str, int]:
    """Undo the area key built by :meth:`AS511Client.locate`."""
    if not (isinstance(area, tuple) and len(area) == 4):
        raise AddressError(f"{area!r} is not an area key of AS511Client.locate")
    letter, db, unit_name, parity = area
    return str(letter), db if isinstance(db, int) else None, str(unit_name), int(parity)


def _area(area: S5Area | str) -> S5Area:
    if isinstance(area, S5Area):
        if area.is_block:
            raise AddressError("use read_db/read_block_bytes for DB and DX")
        return area
    letters = {"I": "E", "Q": "A", "C": "Z"}
    try:
        return _area(S5Area(letters.get(area.upper(), area.upper())))
    except ValueError:
        raise AddressError(f"unknown area {area!r}; use M, I/E, Q/A, T, C/Z") from None


def _check_byte(value: int | bool) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ValueEncodeError(
            f"byte value {value!r} ({type(value).__name__}) is not an integer in 0..255"
        )
    return value


def _pack_words(values: Sequence[int] | Sequence[bool]) -> bytes:
    fast = pack_ints(values, ">", "H")  # plain ints in range: no per-value checks needed
    if fast is not None:
        return fast
    out = bytearray()
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueEncodeError(
                f"word value {value!r} ({type(value).__name__}) is not an integer"
            )
        if not -0x8000 <= value <= 0xFFFF:
            raise AddressError(f"word value {value} is outside -32768..65535")
        out += struct.pack(">H", value & 0xFFFF)
    return bytes(out)
