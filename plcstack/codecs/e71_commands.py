"""E71 commands beyond 00H-09H: both roles, binary and ASCII (spec §7.4-§7.8, §9).

Every request here is an :class:`~plcstack.codecs.e71.ExtensionRequest`: on the client side
:class:`~plcstack.codecs.e71.E71ClientConnection` sends it like a core request (it encodes itself
and sizes/decodes its own response); on the E71 side an
:class:`~plcstack.codecs.e71.E71ServerConnection` built with ``extensions=DECODERS`` hands the
same objects back decoded from the wire. So one class per command is the encoder and the decoder.

* 13H :class:`RemoteRun`, 14H :class:`RemoteStop`, 15H :class:`ReadCpuModel`, 16H :class:`Loopback`
* 0EH :class:`ReadSpecial`, 0FH :class:`WriteSpecial` (special function module buffer memory)
* 17H-1BH :class:`ReadExtFile`, :class:`WriteExtFile`, :class:`TestExtFile`,
  :class:`RegisterMonitorExt`, :class:`MonitorExt`; 3BH/3CH :class:`ReadExtDirect`,
  :class:`WriteExtDirect` (extended file registers)
* 61H/62H :class:`ReadRandomBuffer`, :class:`WriteRandomBuffer` (random access buffer, §9)
* 60H :class:`FixedBufferData` (fixed buffer with procedure, §8.1; either direction)
* 0AH-0DH, 10H-12H, 1CH-21H, 39H, 3AH :class:`OpaqueCommand`: command + raw wire body both ways
  (their layout is not documented, §13 A11); :mod:`plcstack.codecs.e71_programs` offers the
  reconstructed [R] layout of §7.8 as experimental helpers on top.

Responses decode to the core events (:class:`Ack`, :class:`WordsResponse`, :class:`ErrorResponse`)
or to the ones defined here (:class:`BytesResponse`, :class:`CpuModelResponse`,
:class:`LoopbackResponse`, :class:`OpaqueResponse`). The E71 side encodes with the same classes
(plus :class:`RandomBufferResponse` for the §13 A2 ASCII response width).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Final

from plcstack.codecs.e71_command_events import (
    CPU_MODELS,
    EXT_FILE_BLOCK_SIZE,
    FIXED_BUFFER_MAX_WORDS,
    OPAQUE_COMMANDS,
    R_CODE,
    RANDOM_BUFFER_MAX_WORDS,
    RANDOM_BUFFER_WORDS,
    BytesResponse,
    CpuModelResponse,
    LoopbackResponse,
    OpaqueResponse,
    RandomBufferResponse,
    cpu_model_name,
)
from plcstack.codecs.e71_events import (
    Ack,
    ErrorResponse,
    ExtensionRequest,
    ExtensionResponse,
    Response,
    WordsResponse,
)
from plcstack.codecs.e71_wire import (
    DEFAULT_PC,
    DEFAULT_TIMER,
    Code,
    Malformed,
    Reader,
    Writer,
    count_from,
)
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "CPU_MODELS",
    "DECODERS",
    "EXT_FILE_BLOCK_SIZE",
    "FIXED_BUFFER_MAX_WORDS",
    "OPAQUE_COMMANDS",
    "RANDOM_BUFFER_MAX_WORDS",
    "RANDOM_BUFFER_WORDS",
    "R_CODE",
    "BytesResponse",
    "CpuModelResponse",
    "FixedBufferData",
    "Loopback",
    "LoopbackResponse",
    "MonitorExt",
    "OpaqueCommand",
    "OpaqueResponse",
    "RandomBufferResponse",
    "ReadCpuModel",
    "ReadExtDirect",
    "ReadExtFile",
    "ReadRandomBuffer",
    "ReadSpecial",
    "RegisterMonitorExt",
    "RemoteRun",
    "RemoteStop",
    "TestExtFile",
    "WriteExtDirect",
    "WriteExtFile",
    "WriteRandomBuffer",
    "WriteSpecial",
    "cpu_model_name",
]


# ---------------------------------------------------------------------------------------------
# Response framing shared by every command here (§4.3, §11.2)


def _unit(code: Code) -> int:
    return 2 if code is Code.ASCII else 1


def _head(head: bytes, code: Code, expected_sub: int, sub_units: int = 1) -> tuple[int, int] | None:
    """(subheader, end code) from the response start, checking the subheader (§11.3);
    ``None`` when fewer bytes are buffered. ``sub_units`` = 2 for the 6-char RAB form (§13 A2)."""
    u = _unit(code)
    if len(head) < (sub_units + 1) * u:
        return None
    try:
        r = Reader(head[: (sub_units + 1) * u], code is Code.ASCII)
        sub = r.num(1)
        if sub_units == 2:
            r.num(1)
        end = r.num(1)
    except Malformed:
        raise RemoteProtocolError(f"malformed response head {head[:8]!r}") from None
    if sub != expected_sub:
        raise RemoteProtocolError(
            f"response subheader {sub:02X}H does not answer command "
            f"{expected_sub & 0x7F:02X}H (expected {expected_sub:02X}H)"
        )
    return sub, end


def _size(head: bytes, code: Code, command: int, data_len: int, sub_units: int = 1) -> int | None:
    """Whole response length in wire bytes: data of ``data_len`` binary bytes on success, 2 units
    on an error, 3 units on 5BH (its trailing 00H is left to the connection, §13 A3)."""
    got = _head(head, code, (command | 0x80) & 0xFF, sub_units)
    if got is None:
        return None
    u = _unit(code)
    end = got[1]
    if end == 0:
        return (sub_units + 1 + data_len) * u
    if end == 0x5B:
        return (sub_units + 2) * u
    return (sub_units + 1) * u


def _error_or_body(
    frame: bytes, code: Code, command: int, sub_units: int = 1
) -> ErrorResponse | Reader:
    """An :class:`ErrorResponse` for a non-zero end code, else a reader positioned at the data."""
    r = Reader(frame, code is Code.ASCII)
    try:
        r.num(sub_units)
        end = r.num(1)
        if end == 0x5B:
            return ErrorResponse(command, end, r.num(1))
    except Malformed as exc:
        raise RemoteProtocolError(f"malformed {command | 0x80:02X}H response: {exc}") from None
    if end != 0:
        return ErrorResponse(command, end)
    return r


def _malformed(command: int, exc: Malformed) -> RemoteProtocolError:
    return RemoteProtocolError(f"malformed {(command | 0x80) & 0xFF:02X}H response: {exc}")


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise LocalProtocolError(message)


def _is_int(value: object, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _check_words(values: Sequence[int]) -> None:
    for v in values:
        _check(_is_int(v, 0, 0xFFFF), f"word value {v!r} outside 0..65535")


# ---------------------------------------------------------------------------------------------
# Requests with the common header (subheader, PC number, monitoring timer)


def _r_ref(r: Reader, width: int) -> tuple[int, int]:
    """(block, number) of an R designation of 6 (no block) or 8 bytes; 56H for another code."""
    value = r.num(width)
    dcode = value >> 32 & 0xFFFF
    if dcode != R_CODE:
        raise Malformed(0x56, f"device code {dcode:04X}H is not R (5220H)")
    return value >> 48, value & 0xFFFFFFFF


@dataclass(frozen=True, slots=True)
class _Hdr(ExtensionRequest):
    pc: int = field(default=DEFAULT_PC, kw_only=True)
    timer: int = field(default=DEFAULT_TIMER, kw_only=True)

    def _writer(self, code: Code) -> Writer:
        _check(_is_int(self.pc, 0, 0xFF), f"PC number {self.pc!r} outside 00H-FFH")
        _check(_is_int(self.timer, 0, 0xFFFF), f"monitoring timer {self.timer!r} invalid")
        w = Writer(code is Code.ASCII)
        w.num(self.COMMAND, 1)
        w.num(self.pc, 1)
        w.num(self.timer, 2)
        return w

    def _data_length(self) -> int:
        return 0

    def response_size(self, head: bytes, code: Code) -> int | None:
        return _size(head, code, self.COMMAND, self._data_length())

    def decode_response(self, frame: bytes, code: Code) -> Response | ExtensionResponse:
        got = _error_or_body(frame, code, self.COMMAND)
        if isinstance(got, ErrorResponse):
            return got
        try:
            return self._decode_data(got)
        except Malformed as exc:
            raise _malformed(self.COMMAND, exc) from None

    def _decode_data(self, r: Reader) -> Response | ExtensionResponse:
        return Ack(self.COMMAND)

    # -- E71 side: the request decoded from a complete, correctly sized frame ------------------
    @classmethod
    def decode(cls, frame: bytes, code: Code, lower_ok: bool) -> ExtensionRequest:
        """The request in ``frame``; :class:`Malformed` carries the end code and the PC number."""
        r = Reader(frame, code is Code.ASCII, lower_ok=lower_ok)
        r.num(1)
        hdr = {"pc": r.num(1), "timer": r.num(2)}
        try:
            return cls._decode_fields(r, hdr)
        except Malformed as exc:
            exc.pc = hdr["pc"]
            raise

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        """What follows the header (nothing for 13H-15H and 1BH)."""
        return cls(**hdr)


class _WordsReply:
    """The answer is ``count`` words (17H, 1BH, 3BH): one sizing and decoding for all three."""

    __slots__ = ()
    COMMAND: ClassVar[int]
    count: int

    def _data_length(self) -> int:
        return 2 * self.count

    def _decode_data(self, r: Reader) -> Response | ExtensionResponse:
        return WordsResponse(self.COMMAND, r.words(self.count))


@dataclass(frozen=True, slots=True)
class RemoteRun(_Hdr):
    """13H remote RUN (no request data; answer ``93 00``)."""

    COMMAND: ClassVar[int] = 0x13

    def encode(self, code: Code) -> bytes:
        return self._writer(code).getvalue()


@dataclass(frozen=True, slots=True)
class RemoteStop(_Hdr):
    """14H remote STOP (no request data; answer ``94 00``)."""

    COMMAND: ClassVar[int] = 0x14

    def encode(self, code: Code) -> bytes:
        return self._writer(code).getvalue()


@dataclass(frozen=True, slots=True)
class ReadCpuModel(_Hdr):
    """15H read the CPU model code (answer ``95 00 <code> 00``)."""

    COMMAND: ClassVar[int] = 0x15

    def encode(self, code: Code) -> bytes:
        return self._writer(code).getvalue()

    def _data_length(self) -> int:
        return 2

    def _decode_data(self, r: Reader) -> Response | ExtensionResponse:
        model = r.num(1)
        r.num(1)
        return CpuModelResponse(model)


@dataclass(frozen=True, slots=True)
class Loopback(_Hdr):
    """16H loopback test: ``data`` (1-256 bytes; the client allows 1-254, §13 A6) comes back."""

    COMMAND: ClassVar[int] = 0x16
    data: bytes

    def encode(self, code: Code) -> bytes:
        _check(
            isinstance(self.data, bytes) and 1 <= len(self.data) <= 256,
            "loopback data must be 1-256 bytes",
        )
        w = self._writer(code)
        w.num(len(self.data) & 0xFF, 1)
        w.raw(self.data)
        return w.getvalue()

    def _data_length(self) -> int:
        return 1 + len(self.data)

    def _decode_data(self, r: Reader) -> Response | ExtensionResponse:
        n = r.num(1) or 256
        if n != len(self.data):
            raise Malformed(0x57, f"loopback length {n} differs from the {len(self.data)} sent")
        return LoopbackResponse(r.raw(n))

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        n = r.num(1) or 256
        return cls(r.raw(n), **hdr)


@dataclass(frozen=True, slots=True)
class ReadSpecial(_Hdr):
    """0EH special function module buffer memory read: ``count`` bytes (1-256) from byte
    ``address`` (FROM word address x 2 + the module's buffer offset) of module ``module``
    (upper two digits of its last I/O number), §7.5."""

    COMMAND: ClassVar[int] = 0x0E
    module: int
    address: int
    count: int

    def encode(self, code: Code) -> bytes:
        _check(_is_int(self.count, 1, 256), f"byte count {self.count!r} outside 1-256")
        return _special_head(self, code, self.count).getvalue()

    def _data_length(self) -> int:
        return self.count

    def _decode_data(self, r: Reader) -> Response | ExtensionResponse:
        return BytesResponse(self.COMMAND, r.raw(self.count))

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        address, count, module = r.num(3), r.num(1) or 256, r.num(1)
        r.num(1)
        return cls(module, address, count, **hdr)


@dataclass(frozen=True, slots=True)
class WriteSpecial(_Hdr):
    """0FH special function module buffer memory write: ``data`` (1-256 bytes), §7.5."""

    COMMAND: ClassVar[int] = 0x0F
    module: int
    address: int
    data: bytes

    def encode(self, code: Code) -> bytes:
        _check(
            isinstance(self.data, bytes) and 1 <= len(self.data) <= 256,
            "special module write takes 1-256 bytes",
        )
        w = _special_head(self, code, len(self.data))
        w.raw(self.data)
        return w.getvalue()

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        address, count, module = r.num(3), r.num(1) or 256, r.num(1)
        r.num(1)
        return cls(module, address, r.raw(count), **hdr)


def _special_head(req: ReadSpecial | WriteSpecial, code: Code, count: int) -> Writer:
    _check(_is_int(req.address, 0, 0xFFFFFF), f"start address {req.address!r} not 3 bytes")
    _check(_is_int(req.module, 0, 0xFF), f"module number {req.module!r} outside 00H-FFH")
    w = req._writer(code)
    w.num(req.address, 3)
    w.num(count & 0xFF, 1)
    w.num(req.module, 1)
    w.num(0, 1)
    return w


def _xdev(block: int, number: int) -> int:
    """§3 rule 4: the 8-byte unit number(4) + code(2) + block(2) as one little-endian value."""
    _check(_is_int(block, 0, 0xFFFF), f"block number {block!r} outside 0-65535")
    _check(_is_int(number, 0, 0xFFFFFFFF), f"register number {number!r} invalid")
    return block << 48 | R_CODE << 32 | number


def _count_ok(n: int, limit: int, what: str) -> None:
    _check(_is_int(n, 1, limit), f"{what} takes 1-{limit} points, got {n}")


@dataclass(frozen=True, slots=True)
class ReadExtFile(_WordsReply, _Hdr):
    """17H extended file register batch read: ``count`` (1-256) registers from R``number`` of
    ``block``."""

    COMMAND: ClassVar[int] = 0x17
    block: int
    number: int
    count: int

    def encode(self, code: Code) -> bytes:
        _count_ok(self.count, 256, "17H")
        w = self._writer(code)
        w.num(_xdev(self.block, self.number), 8)
        w.num(self.count & 0xFF, 1)
        w.num(0, 1)
        return w.getvalue()

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        block, number = _r_ref(r, 8)
        return cls(block, number, count_from(r), **hdr)


@dataclass(frozen=True, slots=True)
class WriteExtFile(_Hdr):
    """18H extended file register batch write (1-256 words)."""

    COMMAND: ClassVar[int] = 0x18
    block: int
    number: int
    values: tuple[int, ...]

    def encode(self, code: Code) -> bytes:
        _count_ok(len(self.values), 256, "18H")
        _check_words(self.values)
        w = self._writer(code)
        w.num(_xdev(self.block, self.number), 8)
        w.num(len(self.values) & 0xFF, 1)
        w.num(0, 1)
        w.words(self.values)
        return w.getvalue()

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        block, number = _r_ref(r, 8)
        return cls(block, number, r.words(count_from(r)), **hdr)


@dataclass(frozen=True, slots=True)
class TestExtFile(_Hdr):
    """19H extended file register test (random write): ``(block, number, value)`` x 1-40."""

    COMMAND: ClassVar[int] = 0x19
    __test__: ClassVar[bool] = False  # not a pytest class
    points: tuple[tuple[int, int, int], ...]

    def encode(self, code: Code) -> bytes:
        _count_ok(len(self.points), 40, "19H")
        w = self._writer(code)
        w.num(len(self.points), 1)
        w.num(0, 1)
        for block, number, value in self.points:
            _check_words([value])
            w.num(_xdev(block, number), 8)
            w.num(value, 2)
        return w.getvalue()

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        points = []
        for _ in range(count_from(r)):
            block, number = _r_ref(r, 8)
            points.append((block, number, r.num(2)))
        return cls(tuple(points), **hdr)


@dataclass(frozen=True, slots=True)
class RegisterMonitorExt(_Hdr):
    """1AH extended file register monitor registration: ``(block, number)`` x 1-20. Replaces any
    06H/07H registration (one registration per CPU, §7.3)."""

    COMMAND: ClassVar[int] = 0x1A
    points: tuple[tuple[int, int], ...]

    def encode(self, code: Code) -> bytes:
        _count_ok(len(self.points), 20, "1AH")
        w = self._writer(code)
        w.num(len(self.points), 1)
        w.num(0, 1)
        for block, number in self.points:
            w.num(_xdev(block, number), 8)
        return w.getvalue()

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        n = count_from(r)
        return cls(tuple(_r_ref(r, 8) for _ in range(n)), **hdr)


@dataclass(frozen=True, slots=True)
class MonitorExt(_WordsReply, _Hdr):
    """1BH extended file register monitor. ``count`` (not on the wire) = the number of points
    registered by 1AH, needed to size the answer (§11.2)."""

    COMMAND: ClassVar[int] = 0x1B
    count: int = field(default=0, compare=False)

    def encode(self, code: Code) -> bytes:
        _count_ok(self.count, 20, "1BH (registered points)")
        return self._writer(code).getvalue()


@dataclass(frozen=True, slots=True)
class ReadExtDirect(_WordsReply, _Hdr):
    """3BH extended file register direct read (AnA/AnU): ``number`` = (block - 1) x 8192 +
    register (§7.4), 1-256 words."""

    COMMAND: ClassVar[int] = 0x3B
    number: int
    count: int

    def encode(self, code: Code) -> bytes:
        _count_ok(self.count, 256, "3BH")
        _check(_is_int(self.number, 0, 0xFFFFFFFF), f"register number {self.number!r} invalid")
        w = self._writer(code)
        w.num(R_CODE << 32 | self.number, 6)
        w.num(self.count & 0xFF, 1)
        w.num(0, 1)
        return w.getvalue()

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        _, number = _r_ref(r, 6)
        return cls(number, count_from(r), **hdr)


@dataclass(frozen=True, slots=True)
class WriteExtDirect(_Hdr):
    """3CH extended file register direct write (AnA/AnU), 1-256 words."""

    COMMAND: ClassVar[int] = 0x3C
    number: int
    values: tuple[int, ...]

    def encode(self, code: Code) -> bytes:
        _count_ok(len(self.values), 256, "3CH")
        _check_words(self.values)
        _check(_is_int(self.number, 0, 0xFFFFFFFF), f"register number {self.number!r} invalid")
        w = self._writer(code)
        w.num(R_CODE << 32 | self.number, 6)
        w.num(len(self.values) & 0xFF, 1)
        w.num(0, 1)
        w.words(self.values)
        return w.getvalue()

    @classmethod
    def _decode_fields(cls, r: Reader, hdr: dict[str, int]) -> ExtensionRequest:
        _, number = _r_ref(r, 6)
        return cls(number, r.words(count_from(r)), **hdr)


@dataclass(frozen=True, slots=True)
class OpaqueCommand(_Hdr):
    """An undocumented-layout command (§7.8, §13 A11): ``body`` = the raw wire bytes after the
    4-byte / 8-char header (ASCII: the text), ``response_length`` = length of the answer's data
    after the end code in binary bytes (ASCII: twice as many characters); it is not on the wire
    but needed to frame the answer."""

    command: int
    body: bytes = b""
    response_length: int = field(default=0, compare=False)

    @property
    def COMMAND(self) -> int:  # type: ignore[override]
        return self.command

    def encode(self, code: Code) -> bytes:
        _check(self.command in OPAQUE_COMMANDS, f"command {self.command!r} is not opaque here")
        _check(isinstance(self.body, bytes), "body must be bytes")
        return self._writer(code).getvalue() + self.body

    def response_size(self, head: bytes, code: Code) -> int | None:
        return _size(head, code, self.command, self.response_length)

    def decode_response(self, frame: bytes, code: Code) -> Response | ExtensionResponse:
        got = _error_or_body(frame, code, self.command)
        if isinstance(got, ErrorResponse):
            return got
        return OpaqueResponse(self.command, frame[2 * _unit(code) :])

    @classmethod
    def decode(cls, frame: bytes, code: Code, lower_ok: bool) -> ExtensionRequest:
        r = Reader(frame, code is Code.ASCII, lower_ok=lower_ok)
        command = r.num(1)
        pc, timer = r.num(1), r.num(2)
        return cls(command, frame[r.pos :], pc=pc, timer=timer)


# ---------------------------------------------------------------------------------------------
# Random access buffer (61H/62H) and fixed buffer data (60H): "xx 00" subheader, no PC/timer


@dataclass(frozen=True, slots=True)
class _Buffer(ExtensionRequest):
    def _writer(self, code: Code, address: int | None, count: int) -> Writer:
        w = Writer(code is Code.ASCII)
        w.num(self.COMMAND, 1)
        w.num(0, 1)  # §13 A16: always 00H
        if address is not None:
            w.num(address, 2)
        w.num(count, 2)
        return w

    @staticmethod
    def _reader(frame: bytes, code: Code, lower_ok: bool) -> Reader:
        r = Reader(frame, code is Code.ASCII, lower_ok=lower_ok)
        r.num(1)
        r.num(1)  # §13 A16: the second subheader byte is ignored
        return r


def _rab_check(address: int, count: int, code: Code) -> None:
    limit = RANDOM_BUFFER_MAX_WORDS[code]
    _check(_is_int(address, 0, RANDOM_BUFFER_WORDS - 1), f"address {address!r} outside 0-6143")
    _check(_is_int(count, 1, limit), f"{code.value} random access buffer: 1-{limit} words")
    _check(address + count <= RANDOM_BUFFER_WORDS, f"{address} + {count} words runs past 6143")


@dataclass(frozen=True, slots=True)
class ReadRandomBuffer(_Buffer):
    """61H random access buffer read: ``count`` words from internal address ``address``.
    ``ascii_sub_chars`` (not on the wire): 4 = expect the 6-char ``E100``+end form (§13 A2)."""

    COMMAND: ClassVar[int] = 0x61
    address: int
    count: int
    ascii_sub_chars: int = field(default=2, compare=False)

    def encode(self, code: Code) -> bytes:
        _rab_check(self.address, self.count, code)
        return self._writer(code, self.address, self.count).getvalue()

    def _subs(self, code: Code) -> int:
        return 2 if code is Code.ASCII and self.ascii_sub_chars == 4 else 1

    def response_size(self, head: bytes, code: Code) -> int | None:
        return _size(head, code, self.COMMAND, 2 * self.count, self._subs(code))

    def decode_response(self, frame: bytes, code: Code) -> Response | ExtensionResponse:
        got = _error_or_body(frame, code, self.COMMAND, self._subs(code))
        if isinstance(got, ErrorResponse):
            return got
        try:
            return WordsResponse(self.COMMAND, got.words(self.count))
        except Malformed as exc:
            raise _malformed(self.COMMAND, exc) from None

    @classmethod
    def decode(cls, frame: bytes, code: Code, lower_ok: bool) -> ExtensionRequest:
        r = cls._reader(frame, code, lower_ok)
        return cls(r.num(2), r.num(2))


@dataclass(frozen=True, slots=True)
class WriteRandomBuffer(_Buffer):
    """62H random access buffer write of ``values`` at internal address ``address``."""

    COMMAND: ClassVar[int] = 0x62
    address: int
    values: tuple[int, ...]
    ascii_sub_chars: int = field(default=2, compare=False)

    def encode(self, code: Code) -> bytes:
        _rab_check(self.address, len(self.values), code)
        _check_words(self.values)
        w = self._writer(code, self.address, len(self.values))
        w.words(self.values)
        return w.getvalue()

    def _subs(self, code: Code) -> int:
        return 2 if code is Code.ASCII and self.ascii_sub_chars == 4 else 1

    def response_size(self, head: bytes, code: Code) -> int | None:
        return _size(head, code, self.COMMAND, 0, self._subs(code))

    def decode_response(self, frame: bytes, code: Code) -> Response | ExtensionResponse:
        got = _error_or_body(frame, code, self.COMMAND, self._subs(code))
        return got if isinstance(got, ErrorResponse) else Ack(self.COMMAND)

    @classmethod
    def decode(cls, frame: bytes, code: Code, lower_ok: bool) -> ExtensionRequest:
        r = cls._reader(frame, code, lower_ok)
        address, count = r.num(2), r.num(2)
        return cls(address, r.words(count))


@dataclass(frozen=True, slots=True)
class FixedBufferData(_Buffer):
    """60H fixed buffer data telegram with procedure (§8.1), either direction: 1-1017 words
    (ASCII 1-508). The answer is ``E0`` + end code (:class:`Ack` / :class:`ErrorResponse`)."""

    COMMAND: ClassVar[int] = 0x60
    values: tuple[int, ...]

    def encode(self, code: Code) -> bytes:
        limit = FIXED_BUFFER_MAX_WORDS[code]
        _check(1 <= len(self.values) <= limit, f"fixed buffer telegram: 1-{limit} words")
        _check_words(self.values)
        w = self._writer(code, None, len(self.values))
        w.words(self.values)
        return w.getvalue()

    def response_size(self, head: bytes, code: Code) -> int | None:
        return _size(head, code, self.COMMAND, 0)

    def decode_response(self, frame: bytes, code: Code) -> Response | ExtensionResponse:
        got = _error_or_body(frame, code, self.COMMAND)
        return got if isinstance(got, ErrorResponse) else Ack(self.COMMAND)

    @classmethod
    def decode(cls, frame: bytes, code: Code, lower_ok: bool) -> ExtensionRequest:
        r = cls._reader(frame, code, lower_ok)
        return cls(r.words(r.num(2)))


#: every command of this module -> its E71-side decoder (``E71ServerConnection(extensions=)``)
DECODERS: Final[dict[int, Callable[[bytes, Code, bool], ExtensionRequest]]] = {
    **{
        cls.COMMAND: cls.decode
        for cls in (
            ReadSpecial,
            WriteSpecial,
            RemoteRun,
            RemoteStop,
            ReadCpuModel,
            Loopback,
            ReadExtFile,
            WriteExtFile,
            TestExtFile,
            RegisterMonitorExt,
            MonitorExt,
            ReadExtDirect,
            WriteExtDirect,
            FixedBufferData,
            ReadRandomBuffer,
            WriteRandomBuffer,
        )
    },
    **dict.fromkeys(OPAQUE_COMMANDS, OpaqueCommand.decode),
}
