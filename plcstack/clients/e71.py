"""MELSEC A-series E71 client (1E frame) for ``e71+tcp://HOST:PORT`` and ``e71+udp://HOST:PORT``.

URL options (besides ``timeout``/``connect_timeout``):

* ``code=binary|ascii`` - must match the module's DIP switch SW2 (it cannot be detected, §11.4);
* ``pc=FF`` - PC number in hex (FF = the CPU the E71 sits on; 00-40 = MELSECNET stations);
* ``monitoring_timer=N`` - ACPU monitoring timer in 250 ms units. Default: just under the request
  timeout (``4 * timeout - 1``, at least 1), so that a slow CPU is reported by the E71 as end code
  60H before our own deadline closes the connection.

Words are unsigned 16-bit ints (a negative value written is stored two's complement). 32-bit
integers and floats occupy two consecutive words, **low word first at the lower address**, as the
MELSEC CPUs store them (D0 = 0000H, D1 = 3F40H is 0.75, spec §3 rule 10).

``read(address, count)`` is one frame: at most 256 points (bits via 00H, words via 01H);
:meth:`E71Client.read_many` splits longer spans over several frames.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine, Hashable, Sequence
from typing import Any, Self, TypeVar

from plcstack.clients.base import (
    DEFAULT_CONNECT_TIMEOUT,
    DEFAULT_TIMEOUT,
    Points,
    as_points,
)
from plcstack.clients.e71_commands import E71CommandsMixin
from plcstack.clients.exchange import Job
from plcstack.clients.options import COMMON, choice, integer
from plcstack.codecs.e71 import (
    DEFAULT_PC,
    END_CODES,
    WIDEST_RANGES,
    BitsResponse,
    Code,
    Device,
    DeviceRef,
    E71ClientConnection,
    ErrorResponse,
    MonitorBits,
    MonitorWords,
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
    command_limit,
    in_range,
    limit_error,
    parse_address,
    unit_error,
)
from plcstack.codecs.e71_devices import foreign_notation
from plcstack.codecs.e71_wire import as_code
from plcstack.diagnose import Failure, e71_hint
from plcstack.errors import (
    AddressError,
    LocalProtocolError,
    PlcErrorResponse,
    RemoteProtocolError,
    ValueEncodeError,
)
from plcstack.transports import ip_transport
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.transports.udp import UdpTransport
from plcstack.url import PlcUrl
from plcstack.values import FLOAT32, INT32, Endian, plain_words

__all__ = ["MAX_POINTS", "E71Client", "client_code"]

#: a reply type passed through :meth:`E71Client._reply_or_raise` unchanged
R = TypeVar("R")

#: points one read frame carries: 256 bits (00H) or 256 words (01H) (§7.1)
MAX_POINTS = 256
#: most (address, count) word reads a client keeps checked and encoded (a poller reads a few)
_READ_CACHE = 1024


def client_code(code: Code | str, plc: str) -> Code:
    """The frame coding a client of ``plc`` was configured with (the E71 and the fixed-buffer
    client alike); anything but binary or ascii is the user's :class:`AddressError`."""
    try:
        return as_code(code)
    except LocalProtocolError:
        raise AddressError(f"code must be binary or ascii, not {code!r}", plc=plc) from None


def _default_timer(timeout: float) -> int:
    return max(1, min(0xFFFF, int(timeout * 4) - 1))


class E71Client(E71CommandsMixin):
    """Async client for one E71 connection. Use ``async with plcstack.connect(url) as plc``."""

    word_order = Endian.LITTLE  # D100 low word, D101 high word (spec §3 rule 10)
    byte_order = Endian.LITTLE  # "12" in D0 reads 3231H

    OPTIONS = (
        *COMMON,
        choice("code", "binary", ("binary", "ascii"), "must match DIP switch SW2 (§11.4)"),
        integer("pc", DEFAULT_PC, 0, 0xFF, "PC number, hex in a URL (FF = this CPU)", base=16),
        integer("monitoring_timer", None, 0, 0xFFFF, "ACPU monitoring timer, 250 ms units"),
        choice("rab_ascii_sub_chars", 2, (2, 4), "random access buffer ASCII width (§13 A2)"),
    )

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        code: Code | str = Code.BINARY,
        pc: int = DEFAULT_PC,
        monitoring_timer: int | None = None,
        rab_ascii_sub_chars: int = 2,
        timeout: float = DEFAULT_TIMEOUT,
        connect_timeout: float = DEFAULT_CONNECT_TIMEOUT,
        backoff: Backoff | None = None,
    ) -> None:
        super().__init__(
            name, transport, timeout=timeout, connect_timeout=connect_timeout, backoff=backoff
        )
        self.code = client_code(code, name)
        if not (0 <= pc <= 0x40 or pc == 0xFF):
            raise AddressError(f"PC number {pc:#x} is not 00H-40H or FFH", plc=name)
        self.pc = pc
        timer = _default_timer(self.timeout) if monitoring_timer is None else monitoring_timer
        if not 0 <= timer <= 0xFFFF:
            raise AddressError(f"monitoring_timer {timer} outside 0..65535", plc=name)
        self.monitoring_timer = timer
        if rab_ascii_sub_chars not in (2, 4):  # §13 A2, see clients/e71_commands.py
            raise AddressError("rab_ascii_sub_chars must be 2 or 4", plc=name)
        self.rab_ascii_sub_chars = rab_ascii_sub_chars
        self._udp = isinstance(transport, UdpTransport)
        # The monitor registration lives in the PLC, not in the connection: keep what we
        # registered across reconnects so 88H/89H can still be sized.
        self._monitor: tuple[int | None, int | None] = (None, None)
        #: (address, count) -> the exchange of a word read already checked (its 01H request,
        #: which the codec encodes once per connection and whose answer size and word layout
        #: it notes): a poller reads the same few addresses every scan (see ``read``)
        self._word_reads: dict[tuple[str, int], Job] = {}
        #: bound once: a bound method made per read would be one more object per request
        self._finish: Callable[[Response, str], list[int]] = self._finish_words
        self.codec: E71ClientConnection = self.new_codec()

    @classmethod
    def create(cls, url: PlcUrl, options: dict[str, Any]) -> Self:
        transport = ip_transport(url.host, url.port, url.transport)
        return cls(url.raw, transport, **options)

    def diagnose(self, failure: Failure, reply: bytes) -> str:
        if self._udp and not reply:
            return ""  # a datagram that was never answered says nothing about the peer
        return e71_hint(failure, reply, code=self.code.value, first=self.first_ever())

    def new_codec(self) -> E71ClientConnection:
        codec = E71ClientConnection(self.code, transport="udp" if self._udp else "tcp")
        codec.monitor_bits, codec.monitor_words = self._monitor
        return codec

    # -- plumbing -------------------------------------------------------------------------------
    def _hdr(self) -> dict[str, int]:
        return {"pc": self.pc, "timer": self.monitoring_timer}  # pc may be changed at run time

    def _ref(self, address: str, what: str) -> DeviceRef:
        try:
            return parse_address(address)
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=what) from None

    def _bad(self, message: str, what: str) -> AddressError:
        return AddressError(message, plc=self.name, request=what)

    async def _call(self, request: Request, what: str, *, is_write: bool) -> Response:
        event: Response = await self.exchange(request, what, is_write=is_write)
        return self._reply_or_raise(event, what, is_write=is_write)

    def _reply_or_raise(self, event: R, what: str, *, is_write: bool = False) -> R:
        """The reply, or the PLC's end code as :class:`PlcErrorResponse` with its meaning.

        An end code outside the documented table (§10) is no refusal we can vouch for: random
        bytes such as ``83 25`` decode as "end code 25H", and calling that a PLC error would
        tell the caller an executed write was refused. It is a :class:`RemoteProtocolError`
        under the failure policy (connection closed, "may or may not" for a write)."""
        if isinstance(event, ErrorResponse):
            if event.end_code not in END_CODES:
                undocumented = RemoteProtocolError(
                    f"the answer carries end code {event.end_code:02X}H, which the E71 does "
                    "not define (§10); not taken as a refusal"
                )
                raise self.request_failed(
                    undocumented, "malformed", b"", what, is_write=is_write, sent=True
                )
            self.count_error()
            raise PlcErrorResponse(
                event.end_code,
                event.meaning,
                plc=self.name,
                request=what,
                code_text=event.code_text,
            )
        return event

    async def _read_bits(self, request: ReadBits | MonitorBits, what: str) -> list[bool]:
        event = await self._call(request, what, is_write=False)
        if not isinstance(event, BitsResponse):  # pragma: no cover - codec guarantees it
            raise RemoteProtocolError("unexpected response", plc=self.name, request=what)
        return list(event.values)

    async def _read_words(self, request: ReadWords | MonitorWords, what: str) -> list[int]:
        event = await self.exchange(request, what, is_write=False)
        return self._words_of_event(event, what)

    def _words_of_event(self, event: Response, what: str) -> list[int]:
        event = self._reply_or_raise(event, what)
        if not isinstance(event, WordsResponse):  # pragma: no cover - codec guarantees it
            raise RemoteProtocolError("unexpected response", plc=self.name, request=what)
        return list(event.values)

    def _check_span(self, ref: DeviceRef, count: int, limit: int, what: str, unit: int = 1) -> None:
        if not isinstance(count, int) or isinstance(count, bool) or not 1 <= count <= limit:
            raise self._bad(
                f"count must be 1..{limit} for {ref.device.letters}, got {count!r}", what
            )
        if not in_range(ref.device, ref.number, count * unit, WIDEST_RANGES):
            raise self._bad(f"{ref} + {count * unit} points runs past the last device", what)

    def _words_of(self, values: Sequence[int], what: str) -> tuple[int, ...]:
        fast = plain_words(values)
        if fast is not None:
            return fast
        out = []
        for v in values:
            if isinstance(v, bool) or not isinstance(v, int) or not -0x8000 <= v <= 0xFFFF:
                raise ValueEncodeError(
                    f"word value {v!r} ({type(v).__name__}) is not an integer in -32768..65535",
                    plc=self.name,
                    request=what,
                )
            out.append(v & 0xFFFF)
        return tuple(out)

    def _bits_of(self, values: Sequence[bool] | Sequence[int], what: str) -> tuple[bool, ...]:
        out = []
        for v in values:
            if v not in (0, 1) or not isinstance(v, int):
                raise self._bad(f"bit value {v!r} is not true/false (or 1/0)", what)
            out.append(bool(v))
        return tuple(out)

    # -- the common API -------------------------------------------------------------------------
    def read(self, address: str, count: int = 1) -> Coroutine[Any, Any, list[int] | list[bool]]:
        """Bits (``list[bool]``, 00H) of a bit device or words (``list[int]``, 01H); <= 256.

        A word read whose address and count were checked before reuses its request object
        (parsing, range checks and encoding done once; the header fields are compared on every
        call, since ``pc`` and ``monitoring_timer`` may change), and is the exchange coroutine
        itself: no coroutine of its own on the polling hot path. Not ``async`` for that reason;
        every error still comes from awaiting the result, as from any ``async def``.
        """
        job = self._word_reads.get((address, count))
        if job is not None:
            request = job.request
            if request.pc == self.pc and request.timer == self.monitoring_timer:
                return self.exchange(
                    request, job.what, is_write=False, finish=self._finish, words=True
                )
        return self._read(address, count)

    callback_reads = True

    def start_read(self, address: str, count: int, done: Callable[[Any], None]) -> bool:
        """:meth:`read` as a callback exchange (:meth:`RequestClient.start_exchange`), for
        word reads already checked once (``read``'s cache of prepared exchanges)."""
        job = self._word_reads.get((address, count))
        if job is None:
            return False
        request = job.request
        if request.pc != self.pc or request.timer != self.monitoring_timer:
            return False
        return self.start_exchange(job, done)

    def _finish_words(self, event: Response, what: str) -> list[int]:
        if type(event) is WordsResponse:
            return list(event.values)
        return self._words_of_event(event, what)

    async def _read(self, address: str, count: int) -> list[int] | list[bool]:
        what = f"read {address} x{count}"
        ref = self._ref(address, what)
        self._check_span(ref, count, MAX_POINTS, what)
        if ref.device.is_bit:
            return await self._read_bits(
                ReadBits(ref, count, pc=self.pc, timer=self.monitoring_timer), what
            )
        request = ReadWords(ref, count, pc=self.pc, timer=self.monitoring_timer)
        if type(address) is str and type(count) is int:
            if len(self._word_reads) >= _READ_CACHE:
                self._word_reads.clear()
            self._word_reads[(address, count)] = Job(request, what, self._finish, False, True)
        return await self.exchange(request, what, is_write=False, finish=self._finish, words=True)

    async def write(self, address: str, values: Points) -> None:
        """Bits to a bit device (02H) or words to a word device (03H); <= 256 points."""
        values = as_points(values, plc=self.name, request=f"write {address}")
        what = f"write {address} x{len(values)}"
        ref = self._ref(address, what)
        self._check_span(ref, len(values), MAX_POINTS, what)
        if ref.device.is_bit:
            request: Request = WriteBits(ref, self._bits_of(values, what), **self._hdr())
        else:
            words = plain_words(values)  # plain ints in range: no per-value checks needed
            if words is None:
                if any(isinstance(v, bool) for v in values):
                    raise self._bad(f"{ref.device.letters} is a word device: give integers", what)
                words = self._words_of(values, what)
            request = WriteWords(ref, words, pc=self.pc, timer=self.monitoring_timer)
        await self._call(request, what, is_write=True)

    async def read_words(self, address: str, count: int = 1) -> list[int]:
        """01H in word units, also for bit devices (16 points per word, bit 0 = head; the head
        of a bit device must be a multiple of 16)."""
        what = f"read words {address} x{count}"
        ref = self._ref(address, what)
        limit = command_limit(0x01, ref.device)
        self._check_span(ref, count, limit, what, 16 if ref.device.is_bit else 1)
        request = ReadWords(ref, count, **self._hdr())
        problem = unit_error(request)
        if problem:
            raise self._bad(problem, what)
        return await self._read_words(request, what)

    async def write_words(self, address: str, values: Sequence[int]) -> None:
        """03H in word units, also for bit devices (at most 40 words there)."""
        what = f"write words {address} x{len(values)}"
        ref = self._ref(address, what)
        limit = command_limit(0x03, ref.device)
        self._check_span(ref, len(values), limit, what, 16 if ref.device.is_bit else 1)
        request = WriteWords(ref, self._words_of(values, what), **self._hdr())
        problem = unit_error(request)
        if problem:
            raise self._bad(problem, what)
        await self._call(request, what, is_write=True)

    # -- 32-bit helpers (low word first): thin aliases of read_as/write_as ----------------------
    async def read_int32(self, address: str, count: int = 1) -> list[int]:
        """``count`` signed 32-bit integers from ``2 * count`` words, low word first."""
        return await self.read_as(address, INT32, count)

    async def write_int32(self, address: str, values: Sequence[int]) -> None:
        """Signed 32-bit integers, low word first (``write_as(address, UINT32, ...)`` for
        unsigned ones)."""
        await self.write_as(address, INT32, list(values))

    async def read_float(self, address: str, count: int = 1) -> list[float]:
        """``count`` IEEE 754 single floats from ``2 * count`` words, low word first."""
        return await self.read_as(address, FLOAT32, count)

    async def write_float(self, address: str, values: Sequence[float]) -> None:
        await self.write_as(address, FLOAT32, list(values))

    def split_bit(self, address: str) -> tuple[str, int | None]:
        """``D100.3`` / ``D100.F``: bit 0-F (hexadecimal, as GX Developer writes it) of a word."""
        head, dot, tail = address.rpartition(".")
        if not dot:
            return address, None
        if len(tail) != 1 or tail.upper() not in "0123456789ABCDEF":
            foreign = foreign_notation(address)  # DB10.DW0: the family's words, not the bit's
            raise AddressError(
                f"address {address!r}{foreign}"
                if foreign
                else f"{address!r}: the bit of a word is one hexadecimal digit 0-F (D100.F)",
                plc=self.name,
            )
        return head, int(tail, 16)

    # -- many spans ----------------------------------------------------------------------------
    async def read_many(self, items: Sequence[tuple[str, int]]) -> list[list[int] | list[bool]]:
        """Read several ``(address, count)`` spans; each is split into frames of at most 256
        points (not atomic across frames). Returns one list per item."""
        out: list[list[int] | list[bool]] = []
        for address, count in items:
            area, index = self.locate(address, count)
            limit = self.max_points(area)
            values: list[Any] = []
            done = 0
            while done < count:
                n = min(limit, count - done)
                values.extend(await self.read(self.address_at(area, index + done), n))
                done += n
            out.append(values)
        return out

    # -- poller hooks --------------------------------------------------------------------------
    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        what = f"locate {address} x{count}"
        ref = self._ref(address, what)
        if not isinstance(count, int) or count < 1:
            raise self._bad(f"count must be >= 1, got {count!r}", what)
        if not in_range(ref.device, ref.number, count, WIDEST_RANGES):
            raise self._bad(f"{ref} + {count} points runs past the last device", what)
        return ref.device, ref.number

    def address_at(self, area: Hashable, index: int) -> str:
        if not isinstance(area, Device):
            raise AddressError(f"not an E71 area: {area!r}", plc=self.name)
        return area.format_number(index)

    def max_points(self, area: Hashable) -> int:
        return MAX_POINTS

    def point_bits(self, area: Hashable) -> int:
        """1 for bit devices (``read`` returns bools there), 16 for word devices."""
        if not isinstance(area, Device):
            raise AddressError(f"not an E71 area: {area!r}", plc=self.name)
        return 1 if area.is_bit else 16

    # -- test and monitor (04H-09H) ------------------------------------------------------------
    async def test_bits(self, points: Sequence[tuple[str, bool]]) -> None:
        """04H: set/reset scattered bit points (at most 80)."""
        what = f"test bits x{len(points)}"
        pairs = tuple((self._ref(a, what), v) for a, v in points)
        bits = self._bits_of([v for _, v in pairs], what)
        request = TestBits(
            tuple((r, b) for (r, _), b in zip(pairs, bits, strict=True)), **self._hdr()
        )
        await self._call(self._checked(request, what), what, is_write=True)

    async def test_words(self, points: Sequence[tuple[str, int]]) -> None:
        """05H: write scattered words (at most 40; bit devices: 16-point heads)."""
        what = f"test words x{len(points)}"
        refs = [self._ref(a, what) for a, _ in points]
        words = self._words_of([v for _, v in points], what)
        request = TestWords(tuple(zip(refs, words, strict=True)), **self._hdr())
        await self._call(self._checked(request, what), what, is_write=True)

    async def register_monitor_bits(self, addresses: Sequence[str]) -> None:
        """06H: register up to 40 bit points for :meth:`monitor_bits`."""
        what = f"register monitor bits x{len(addresses)}"
        request = RegisterMonitorBits(tuple(self._ref(a, what) for a in addresses), **self._hdr())
        await self._call(self._checked(request, what), what, is_write=False)
        self._monitor = (len(addresses), None)

    async def register_monitor_words(self, addresses: Sequence[str]) -> None:
        """07H: register up to 20 words (bit devices: 16-point heads) for :meth:`monitor_words`."""
        what = f"register monitor words x{len(addresses)}"
        request = RegisterMonitorWords(tuple(self._ref(a, what) for a in addresses), **self._hdr())
        await self._call(self._checked(request, what), what, is_write=False)
        self._monitor = (None, len(addresses))

    async def monitor_bits(self) -> list[bool]:
        what = "monitor bits"
        if self._monitor[0] is None:
            raise LocalProtocolError(
                "register bit points first (register_monitor_bits)", plc=self.name, request=what
            )
        return await self._read_bits(MonitorBits(**self._hdr()), what)

    async def monitor_words(self) -> list[int]:
        what = "monitor words"
        if self._monitor[1] is None:
            raise LocalProtocolError(
                "register words first (register_monitor_words)", plc=self.name, request=what
            )
        return await self._read_words(MonitorWords(**self._hdr()), what)

    def _checked(self, request: Request, what: str) -> Request:
        problem = limit_error(request) or unit_error(request)
        if problem:
            raise self._bad(problem, what)
        return request
