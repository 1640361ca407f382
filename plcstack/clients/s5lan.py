"""Async client for the Siemens S5-LAN-LINK module: ``s5lan://HOST:PORT``.

    async with plcstack.connect("s5lan://192.168.0.20:5010") as plc:
        words = await plc.read("DB10.DW5", 20)      # list[int], 0..65535
        await plc.write("MB100", [0xDE, 0xAD])

Addresses are S5 notation (:mod:`plcstack.s5address`). Values:

* words (``DB10.DW5``, ``MW10``, ``EW0``, ``T5``, ``Z5``) are read as **unsigned** 16-bit ints
  0..65535; a write takes -32768..65535 and sends negatives as two's complement (INT), so
  ``-1`` and ``65535`` write the same word. Timer/counter words are raw S5 words (no BCD decoding).
* bytes (``MB100``, ``EB0``, ``AB0``, ``DB10.DL5``/``DR5``/``DBB3``) are read as 0..255; a write
  takes -128..255 (negatives as two's complement).
* DB/DX bytes are read through the covering data words (the module transfers D and X as words
  only). Writing single DB bytes is refused: it would need a read-modify-write that another
  writer could interleave with; write the whole data word instead.

Requests larger than the module's 2048 data bytes are split into several requests. A split read
returns all values or raises. A split write that fails part-way raises with a message saying how
many values were confirmed written, because S5-LAN has no way to make it atomic.

Each request's deadline is ``max(timeout, 2 * (50 ms + 1.5 ms/byte) + 1 s)`` (spec A.8 [R]):
reading 2048 bytes takes the module about 3.1 s, so a fixed 2 s deadline would kill healthy reads.

The module accepts one connection at a time and closes any further one at once. The client cannot
tell that from other reasons to close, and its request was already sent, so it is reported as
:class:`~plcstack.errors.ConnectionLost` (for a write: "may or may not have been executed") with
a hint naming the one-connection rule as one possible cause; the next attempt waits for the
backoff, as after a refused connect.
"""

from __future__ import annotations

import enum
import logging
import struct
from collections.abc import Hashable, Sequence
from typing import Any, NamedTuple, Self

from plcstack.clients.base import (
    DEFAULT_CONNECT_TIMEOUT,
    DEFAULT_TIMEOUT,
    Points,
    as_points,
)
from plcstack.clients.exchange import RequestClient
from plcstack.clients.options import COMMON, choice, flag
from plcstack.clients.s5access import S5Access
from plcstack.codecs.s5lan import (
    HEADER_BYTE_ORDER,
    MAX_DATA_BYTES,
    ByteOrder,
    ClientConnection,
    Request,
    Response,
    byte_order_hint,
    err_meaning,
    estimate_seconds,
    swap_words,
)
from plcstack.diagnose import Failure, s5lan_hint
from plcstack.errors import (
    AddressError,
    PlcError,
    PlcErrorResponse,
    ValueEncodeError,
)
from plcstack.s5address import S5Address, S5Area, S5Unit, parse_s5_address
from plcstack.transports.backoff import Backoff
from plcstack.transports.tcp import TcpTransport
from plcstack.url import PlcUrl
from plcstack.values import pack_ints

__all__ = ["S5LanClient"]

_log = logging.getLogger(__name__)

_LETTER = {
    S5Area.DB: "D",
    S5Area.DX: "X",
    S5Area.FLAGS: "M",
    S5Area.INPUTS: "E",
    S5Area.OUTPUTS: "A",
    S5Area.TIMERS: "T",
    S5Area.COUNTERS: "Z",
}
_MAX_START = 0xFFFF
#: most (address, count) plans a client keeps per kind (a poller reads a fixed set of tags)
_PLAN_CACHE = 1024


class _Kind(enum.Enum):
    WORDS = "words"
    BYTES = "bytes"
    DB_BYTES = "DB/DX bytes read through their data words"


class _Plan(NamedTuple):
    """A checked read or write: what the user asked and the wire requests that do it."""

    addr: S5Address  # as given by the user
    what: str  # "read DB10.DW0 x64", for messages
    letter: str  # DataArea
    data_type: str  # DataType on the wire: "W" or "B"
    db: int
    chunks: tuple[tuple[int, int], ...]  # (Start, Count) of each request (<= 2048 bytes)
    size: int  # bytes per wire unit
    kind: _Kind


#: ``locate`` area key: (area, unit, DB number or None, byte parity of M/E/A words)
AreaKey = tuple[S5Area, S5Unit, int | None, int]


def _area_key(area: Hashable) -> AreaKey:
    """Check that ``area`` came from :meth:`S5LanClient.locate`."""
    if (
        isinstance(area, tuple)
        and len(area) == 4
        and isinstance(area[0], S5Area)
        and isinstance(area[1], S5Unit)
    ):
        return area
    raise AddressError(f"{area!r} is not an S5-LAN area key from locate()")


class S5LanClient(S5Access, RequestClient[Response]):
    """One S5-LAN module (and so one PLC). See the module docstring for values and limits."""

    OPTIONS = (
        *COMMON,
        choice("header_byte_order", "little", ("little", "big"), "byte order of the header (A.3)"),
        flag("strict", True, "check every echoed header field of an answer"),
    )
    #: a module closes every connection beyond its one at once (A.2): back off at the first
    UNPROVEN_FAILURES_BEFORE_BACKOFF = 1

    def __init__(
        self,
        name: str,
        host: str,
        port: int,
        *,
        header_byte_order: ByteOrder = HEADER_BYTE_ORDER,
        strict: bool = True,
        timeout: float = DEFAULT_TIMEOUT,
        connect_timeout: float = DEFAULT_CONNECT_TIMEOUT,
        backoff: Backoff | None = None,
    ) -> None:
        super().__init__(
            name,
            TcpTransport(host, port),
            timeout=timeout,
            connect_timeout=connect_timeout,
            backoff=backoff,
        )
        if header_byte_order not in ("little", "big"):
            raise AddressError(
                f"header_byte_order must be little or big, not {header_byte_order!r}"
            )
        self.header_byte_order: ByteOrder = header_byte_order
        self.strict = strict
        self._seq = 0
        self._read_plans: dict[tuple[str, int], _Plan] = {}
        self._write_plans: dict[tuple[str, int], _Plan] = {}
        self.codec: ClientConnection = self.new_codec()

    @classmethod
    def create(cls, url: PlcUrl, options: dict[str, Any]) -> Self:
        """``s5lan://HOST:PORT[?timeout=S&connect_timeout=S&header_byte_order=little|big&strict=1]``."""
        assert url.host is not None and url.port is not None
        return cls(url.raw, url.host, url.port, **options)

    def diagnose(self, failure: Failure, reply: bytes) -> str:
        return s5lan_hint(failure, reply, first=self.first_on_connection())

    def new_codec(self) -> ClientConnection:
        return ClientConnection(header_byte_order=self.header_byte_order, strict=self.strict)

    # -- poller hooks ------------------------------------------------------------------------
    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        addr = self._parse(address, count)
        phase = addr.offset % 2 if addr.step == 2 else 0
        key: AreaKey = (addr.area, addr.unit, addr.db, phase)
        return key, addr.offset // addr.step

    def address_at(self, area: Hashable, index: int) -> str:
        kind, unit, db, phase = _area_key(area)
        probe = S5Address(kind, unit, 0, db)
        return str(S5Address(kind, unit, index * probe.step + phase, db))

    def max_points(self, area: Hashable) -> int:
        kind, unit, _db, _phase = _area_key(area)
        if unit is S5Unit.WORD:
            return MAX_DATA_BYTES // 2
        # DB/DX bytes go through words; an odd start needs one word more
        return MAX_DATA_BYTES - 2 if kind.is_block else MAX_DATA_BYTES

    def point_bits(self, area: Hashable) -> int:
        """Width of one point of ``area`` for the poller: 16 for words, 8 for bytes."""
        return 16 if _area_key(area)[1] is S5Unit.WORD else 8

    # -- the API -------------------------------------------------------------------------------
    async def read(self, address: str, count: int = 1) -> list[int]:
        plan = (
            self._read_plans.get((address, count))
            if type(address) is str and type(count) is int
            else None
        )
        if plan is None:
            plan = self._plan(address, count, write=False)
        wire = await self._read_wire(plan)
        if plan.kind is _Kind.WORDS:
            return list(struct.unpack(f"<{count}H", wire))
        if plan.kind is _Kind.BYTES:
            return list(wire)
        # DB/DX bytes through their words: wire words are low byte first, and the DB byte
        # DL n is the high byte of DW n
        skip = plan.addr.offset % 2
        return list(swap_words(wire)[skip : skip + count])

    async def write(self, address: str, values: Points) -> None:
        values = as_points(values, plc=self.name, request=f"write {address}")
        n = len(values)
        plan = self._write_plans.get((address, n)) if type(address) is str else None
        if plan is None:
            plan = self._plan(address, n, write=True)
        data = self._encode_values(plan.addr, values)
        size, chunks = plan.size, plan.chunks
        done = 0
        for part, (start, units) in enumerate(chunks):
            req = Request.write(
                plan.letter,
                plan.data_type,
                start,
                data if len(chunks) == 1 else data[done * size : (done + units) * size],
                db=plan.db,
                user_code=self._next_user_code(),
            )
            label = (
                plan.what
                if len(chunks) == 1
                else f"{plan.what} (part {part + 1}: {units} at {start})"
            )
            try:
                await self._request(req, label, is_write=True, total=plan.what)
            except PlcError as exc:
                if done:
                    exc.message += (
                        f"; the first {done} of {n} values were written and confirmed, "
                        "the rest were not (S5-LAN cannot write more than 2048 bytes atomically)"
                    )
                raise
            done += units

    # -- internals -----------------------------------------------------------------------------
    def _plan(self, address: str, count: int, *, write: bool) -> _Plan:
        """Parse and check a request once and work out its wire requests; cached per
        ``(address, count)``, so a poller's repeated reads and writes skip all of it."""
        addr = self._parse(address, count, write=write)
        wire, wire_count, kind = addr, count, _Kind.WORDS
        if addr.area.is_block and addr.unit is S5Unit.BYTE:
            # read through the covering data words (the module moves D and X as words only)
            first, last = addr.offset // 2, (addr.offset + count - 1) // 2
            wire = S5Address(addr.area, S5Unit.WORD, first, addr.db)
            wire_count, kind = last - first + 1, _Kind.DB_BYTES
        elif addr.unit is S5Unit.BYTE:
            kind = _Kind.BYTES
        plan = _Plan(
            addr=addr,
            what=f"{'write' if write else 'read'} {addr} x{count}",
            letter=_LETTER[addr.area],
            data_type="W" if wire.unit is S5Unit.WORD else "B",
            db=addr.db or 0,
            chunks=tuple(self._chunks(wire, wire_count)),
            size=wire.unit.size,
            kind=kind,
        )
        cache = self._write_plans if write else self._read_plans
        if type(address) is str and type(count) is int and len(cache) < _PLAN_CACHE:
            cache[(address, count)] = plan
        return plan

    def _parse(self, address: str, count: int, *, write: bool = False) -> S5Address:
        try:
            addr = parse_s5_address(address)
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise AddressError(f"count must be a positive integer, not {count!r}")
            if write and addr.area.is_block and addr.unit is S5Unit.BYTE:
                raise AddressError(
                    f"S5-LAN writes {addr.area.value} blocks only in whole data words; "
                    f"write {addr.area.value}{addr.db}.DW{addr.offset // 2} instead (a byte "
                    "write would be a non-atomic read-modify-write)"
                )
            last_start = addr.offset + (count - 1) * addr.step
            if addr.area.is_block and addr.unit is S5Unit.BYTE:
                last_start //= 2  # read through the covering data words
            if last_start > _MAX_START:
                raise AddressError(
                    f"{count} points from {addr} go beyond the 16-bit Start field of S5-LAN"
                )
        except AddressError as exc:
            verb = "write" if write else "read"
            raise exc.bind(plc=self.name, request=f"{verb} {address} x{count}") from None
        return addr

    @staticmethod
    def _chunks(addr: S5Address, count: int) -> list[tuple[int, int]]:
        """``(Start, Count)`` of each request for ``count`` points at ``addr`` (<= 2048 bytes)."""
        per = MAX_DATA_BYTES // addr.unit.size
        if count <= per:
            return [(addr.offset, count)]
        out = []
        done = 0
        while done < count:
            units = min(per, count - done)
            out.append((addr.offset + done * addr.step, units))
            done += units
        return out

    async def _read_wire(self, plan: _Plan) -> bytes:
        chunks, what = plan.chunks, plan.what
        parts = []
        for part, (start, units) in enumerate(chunks):
            req = Request.read(
                plan.letter,
                plan.data_type,
                start,
                units,
                db=plan.db,
                user_code=self._next_user_code(),
            )
            label = what if len(chunks) == 1 else f"{what} (part {part + 1} of {len(chunks)})"
            response = await self._request(req, label, is_write=False, total=what)
            if len(chunks) == 1:
                return response.data
            parts.append(response.data)
        return b"".join(parts)

    async def _request(self, req: Request, what: str, *, is_write: bool, total: str) -> Response:
        n = req.header.data_len or 0
        deadline = max(self.timeout, 2.0 * estimate_seconds(n) + 1.0)
        response: Response = await self.exchange(req, what, is_write=is_write, timeout=deadline)
        if response.echo_mismatch:
            _log.warning(
                "%s: %s: answer echoes %s differently from the request (accepted, strict=0)",
                self.name,
                what,
                ", ".join(response.echo_mismatch),
            )
        if response.err != 0:
            self.count_error()
            raise PlcErrorResponse(
                response.err,
                err_meaning(response.err)
                + byte_order_hint(response.header, self.header_byte_order),
                plc=self.name,
                request=what,
                code_text=f"Err {response.err}",
            )
        return response

    def _next_user_code(self) -> bytes:
        # The module echoes UserCode unchanged: a sequence number there proves that an answer
        # belongs to this request, on top of the echoed area/start/count.
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        return self._seq.to_bytes(4, "little")

    def _encode_values(self, addr: S5Address, values: Sequence[int] | Sequence[bool]) -> bytes:
        word = addr.unit is S5Unit.WORD
        fast = pack_ints(values, "<", "H" if word else "B")  # low byte first on the wire (A.6)
        if fast is not None:
            return fast
        lo, hi = (-0x8000, 0xFFFF) if word else (-0x80, 0xFF)
        out = bytearray()
        for i, value in enumerate(values):
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueEncodeError(
                    f"value #{i} {value!r} ({type(value).__name__}) is not an integer "
                    "(S5-LAN has no bit access)",
                    plc=self.name,
                    request=f"write {addr}",
                )
            if not lo <= value <= hi:
                raise AddressError(
                    f"value #{i} {value} is outside {lo}..{hi} for a {'word' if word else 'byte'}",
                    plc=self.name,
                    request=f"write {addr}",
                )
            if word:
                out += struct.pack("<H", value & 0xFFFF)  # low byte first on the wire (A.6)
            else:
                out.append(value & 0xFF)
        return bytes(out)
