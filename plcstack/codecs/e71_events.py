"""E71 events (spec §4, §7.1-§7.3): the requests 00H-09H, their responses, and the hook by which
the commands of :mod:`plcstack.codecs.e71_commands` join them.

Every request encodes itself (``request.encode(code) -> bytes``): the core requests here through
one shared header-and-checks path, the extension requests by their own ``encode``; the
connection calls the same method for both. Responses are plain frozen dataclasses;
:func:`encode_response` renders them for the E71 side.
"""

from __future__ import annotations

import abc
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import ClassVar, Final, Generic, TypeVar

from plcstack.codecs._common import Event, slot_init
from plcstack.codecs.e71_devices import DeviceRef, check_ref, dev_value
from plcstack.codecs.e71_end_codes import ABNORMAL_CODES, END_CODES
from plcstack.codecs.e71_limits import command_limit, head_ok, limit_error, unit_error
from plcstack.codecs.e71_wire import DEFAULT_PC, DEFAULT_TIMER, Code, Writer, pack_bits
from plcstack.errors import LocalProtocolError

__all__ = [
    "REQUEST_TYPES",
    "Ack",
    "BadRequest",
    "BitsResponse",
    "E71Request",
    "ErrorResponse",
    "ExtensionDecoders",
    "ExtensionRequest",
    "ExtensionResponse",
    "MonitorBits",
    "MonitorWords",
    "OpaqueRequest",
    "ReadBits",
    "ReadWords",
    "RegisterMonitorBits",
    "RegisterMonitorWords",
    "Request",
    "Response",
    "TestBits",
    "TestWords",
    "WordsResponse",
    "WriteBits",
    "WriteWords",
    "encode_request",
    "encode_response",
]


class E71Request(Event):
    """Every request the partner sends: it knows its command code and encodes itself.

    A plain base rather than an ``abc.ABC``: ``isinstance`` on the core request classes is on
    the polling hot path, and ``ABCMeta.__instancecheck__`` would triple its cost.
    """

    __slots__ = ()
    COMMAND: ClassVar[int]

    def encode(self, code: Code) -> bytes:
        """The request on the wire; :class:`LocalProtocolError` for values outside the spec."""
        raise NotImplementedError


def _check_word(value: int) -> None:
    if not isinstance(value, int) or not 0 <= value <= 0xFFFF:
        raise LocalProtocolError(f"word value {value!r} outside 0..65535")


#: subheader, PC number, timer, device number, device code, count, 00H of 00H-03H (binary)
_READ_FRAME: Final = struct.Struct("<BBHIHBB")
#: the value of one point of a test (random write) request: a bit's state or a word
_V = TypeVar("_V")
#: what ``_check_word`` accepts as a type (``bool`` is an ``int``)
_INT_OR_BOOL: Final = frozenset({int, bool})


@dataclass(frozen=True, slots=True)
class _Header(E71Request):
    """Subheader, PC number and monitoring timer (§4.2): the head of every request 00H-09H."""

    pc: int = field(default=DEFAULT_PC, kw_only=True)
    timer: int = field(default=DEFAULT_TIMER, kw_only=True)

    def device_refs(self) -> tuple[DeviceRef, ...]:
        return ()

    def point_count(self) -> int:
        return 0

    def encode(self, code: Code) -> bytes:
        """Check the request against §7.1/§7.3 (:class:`LocalProtocolError` on misuse), then
        write the header and the request's own fields."""
        pc, timer = self.pc, self.timer
        if not (
            isinstance(pc, int)
            and isinstance(timer, int)
            and 0 <= pc <= 0xFF
            and 0 <= timer <= 0xFFFF
        ):
            raise LocalProtocolError(
                f"PC number {self.pc!r} or monitoring timer {self.timer!r} invalid"
            )
        for ref in self.device_refs():
            check_ref(ref)
        problem = limit_error(self) or unit_error(self)
        if problem is not None:
            raise LocalProtocolError(problem)
        w = Writer(code is Code.ASCII)
        w.num(self.COMMAND, 1)
        w.num(self.pc, 1)
        w.num(self.timer, 2)
        self._fields(w, self.point_count() & 0xFF)  # 256 -> 00H (§6.4)
        return w.getvalue()

    def _fields(self, w: Writer, n: int) -> None:
        """Write what follows the header; ``n`` is the count field's byte."""


@dataclass(frozen=True, slots=True)
class _Batch(_Header):
    """00H-03H: head device, count field, then (writes) the data."""

    ref: DeviceRef

    def device_refs(self) -> tuple[DeviceRef, ...]:
        return (self.ref,)

    def _fields(self, w: Writer, n: int) -> None:
        w.num(dev_value(self.ref), 6)
        w.num(n, 1)
        w.num(0, 1)


@dataclass(frozen=True, slots=True)
class _BatchRead(_Batch):
    """00H/01H: a batch read of ``count`` points (bit units) or words (word units)."""

    #: True for 00H (bit units: bit devices only), False for 01H (word units)
    BIT_UNIT: ClassVar[bool]
    count: int

    def point_count(self) -> int:
        return self.count

    def encode(self, code: Code) -> bytes:
        if code is Code.BINARY and (data := _fast_read(self)) is not None:
            return data
        return _Header.encode(self, code)


def _fast_read(req: _BatchRead) -> bytes | None:
    """The polling hot path of 00H/01H in binary: the checks of :meth:`_Header.encode`,
    inlined, and one struct call; ``None`` sends the request down the general path."""
    ref, count, pc, timer = req.ref, req.count, req.pc, req.timer
    # exact types: a bool, float or stranger goes the general path, which decides about it
    if type(ref) is not DeviceRef or not type(count) is type(pc) is type(timer) is int:
        return None
    dev, number = ref.device, ref.number
    if (
        1 <= count <= command_limit(req.COMMAND, dev)
        and (dev.is_bit if req.BIT_UNIT else head_ok(ref))
        and 0 <= pc <= 0xFF
        and 0 <= timer <= 0xFFFF
        and type(number) is int
        and 0 <= number <= 0xFFFFFFFF
    ):
        return _READ_FRAME.pack(req.COMMAND, pc, timer, number, dev.code, count & 0xFF, 0)
    return None


@slot_init
@dataclass(frozen=True, slots=True)
class ReadBits(_BatchRead):
    """00H: batch read in bit units (bit devices), 1-256 points."""

    COMMAND: ClassVar[int] = 0x00
    BIT_UNIT: ClassVar[bool] = True


@slot_init
@dataclass(frozen=True, slots=True)
class ReadWords(_BatchRead):
    """01H: batch read in word units; for bit devices ``count`` is in words of 16 points."""

    COMMAND: ClassVar[int] = 0x01
    BIT_UNIT: ClassVar[bool] = False


@slot_init
@dataclass(frozen=True, slots=True)
class WriteBits(_Batch):
    """02H: batch write in bit units."""

    COMMAND: ClassVar[int] = 0x02
    values: tuple[bool, ...]

    def point_count(self) -> int:
        return len(self.values)

    def _fields(self, w: Writer, n: int) -> None:
        _Batch._fields(self, w, n)
        w.raw(pack_bits(self.values))


@slot_init
@dataclass(frozen=True, slots=True)
class WriteWords(_Batch):
    """03H: batch write in word units (bit devices: 16 points per word, bit 0 = head)."""

    COMMAND: ClassVar[int] = 0x03
    values: tuple[int, ...]

    def point_count(self) -> int:
        return len(self.values)

    def encode(self, code: Code) -> bytes:
        if code is Code.BINARY:
            # The write hot path: the checks of the general path, with the per-value
            # ``_check_word`` loop replaced by one type check and ``struct``'s own range check.
            ref, values = self.ref, self.values
            n = len(values)
            if (
                type(ref) is DeviceRef
                and 1 <= n <= command_limit(0x03, ref.device)
                and head_ok(ref)
                and 0 <= self.pc <= 0xFF
                and 0 <= self.timer <= 0xFFFF
                and 0 <= ref.number <= 0xFFFFFFFF
                and set(map(type, values)) <= _INT_OR_BOOL
            ):
                try:
                    data = struct.pack(f"<{n}H", *values)
                except struct.error:
                    pass  # a value out of range: the general path names it
                else:
                    head = _READ_FRAME.pack(
                        0x03, self.pc, self.timer, ref.number, ref.device.code, n & 0xFF, 0
                    )
                    return head + data
        return _Header.encode(self, code)

    def _fields(self, w: Writer, n: int) -> None:
        for v in self.values:
            _check_word(v)
        _Batch._fields(self, w, n)
        w.words(self.values)


@dataclass(frozen=True, slots=True)
class _Test(_Header, Generic[_V]):
    """04H/05H: test (random write): ``(device, value)`` pairs after the count field."""

    __test__: ClassVar[bool] = False  # not a pytest class
    points: tuple[tuple[DeviceRef, _V], ...]

    def device_refs(self) -> tuple[DeviceRef, ...]:
        return tuple(p[0] for p in self.points)

    def point_count(self) -> int:
        return len(self.points)

    def _fields(self, w: Writer, n: int) -> None:
        w.num(n, 1)
        w.num(0, 1)
        for ref, value in self.points:
            w.num(dev_value(ref), 6)
            self._value(w, value)

    def _value(self, w: Writer, value: _V) -> None:
        """Write one point's new value."""
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class TestBits(_Test[bool]):
    """04H: test (random write) in bit units: ``(point, state)`` pairs."""

    COMMAND: ClassVar[int] = 0x04

    def _value(self, w: Writer, value: bool) -> None:
        w.num(1 if value else 0, 1)


@dataclass(frozen=True, slots=True)
class TestWords(_Test[int]):
    """05H: test (random write) in word units: ``(head, word)`` pairs."""

    COMMAND: ClassVar[int] = 0x05

    def _value(self, w: Writer, value: int) -> None:
        _check_word(value)
        w.num(value, 2)


@dataclass(frozen=True, slots=True)
class _Register(_Header):
    refs: tuple[DeviceRef, ...]

    def device_refs(self) -> tuple[DeviceRef, ...]:
        return tuple(self.refs)

    def point_count(self) -> int:
        return len(self.refs)

    def _fields(self, w: Writer, n: int) -> None:
        w.num(n, 1)
        w.num(0, 1)
        for ref in self.refs:
            w.num(dev_value(ref), 6)


@dataclass(frozen=True, slots=True)
class RegisterMonitorBits(_Register):
    """06H: register bit points for monitoring with 08H."""

    COMMAND: ClassVar[int] = 0x06


@dataclass(frozen=True, slots=True)
class RegisterMonitorWords(_Register):
    """07H: register words (word devices, or 16-point heads of bit devices) for 09H."""

    COMMAND: ClassVar[int] = 0x07


@dataclass(frozen=True, slots=True)
class MonitorBits(_Header):
    """08H: read the points registered by 06H."""

    COMMAND: ClassVar[int] = 0x08


@dataclass(frozen=True, slots=True)
class MonitorWords(_Header):
    """09H: read the words registered by 07H."""

    COMMAND: ClassVar[int] = 0x09


@dataclass(frozen=True, slots=True)
class OpaqueRequest(Event):
    """A defined command this version does not interpret (server side): the whole raw frame.

    ``frame`` is exactly the bytes received (ASCII text for ASCII), so a later version can parse
    it; the framing (its length) is already right, so the stream stays in step.
    """

    command: int
    frame: bytes


@dataclass(frozen=True, slots=True)
class BadRequest(Event):
    """A request the E71 answers with ``end_code`` without executing it (server side).

    ``pc`` is the PC number when it could be read (a wrong PC number takes precedence over most
    format errors, §10.3); ``None`` when not (e.g. an ASCII conversion error, 54H).
    ``reason`` is for logs only.
    """

    command: int
    end_code: int
    pc: int | None = None
    reason: str = ""


Request = (
    ReadBits
    | ReadWords
    | WriteBits
    | WriteWords
    | TestBits
    | TestWords
    | RegisterMonitorBits
    | RegisterMonitorWords
    | MonitorBits
    | MonitorWords
)
REQUEST_TYPES: Final = (
    ReadBits,
    ReadWords,
    WriteBits,
    WriteWords,
    TestBits,
    TestWords,
    RegisterMonitorBits,
    RegisterMonitorWords,
    MonitorBits,
    MonitorWords,
)


@slot_init
@dataclass(frozen=True, slots=True)
class Ack(Event):
    """Normal completion without data (82H-87H)."""

    command: int


@slot_init
@dataclass(frozen=True, slots=True)
class BitsResponse(Event):
    """Normal completion with bit data in bit units (80H, 88H)."""

    command: int
    values: tuple[bool, ...]


@slot_init
@dataclass(frozen=True, slots=True)
class WordsResponse(Event):
    """Normal completion with words (81H, 89H)."""

    command: int
    values: tuple[int, ...]


@slot_init
@dataclass(frozen=True, slots=True)
class ErrorResponse(Event):
    """Abnormal completion: ``end_code`` and, after 5BH, the ``abnormal_code`` (§4.3, §10)."""

    command: int
    end_code: int
    abnormal_code: int | None = None

    @property
    def code_text(self) -> str:
        if self.abnormal_code is None:
            return f"{self.end_code:02X}H"
        return f"{self.end_code:02X}H/{self.abnormal_code:02X}H"

    @property
    def meaning(self) -> str:
        text = END_CODES.get(self.end_code, "undocumented end code")
        if self.abnormal_code is not None:
            detail = ABNORMAL_CODES.get(self.abnormal_code, "undocumented abnormal code")
            text = f"{text}: {detail}"
        return text


Response = Ack | BitsResponse | WordsResponse | ErrorResponse


# ---------------------------------------------------------------------------------------------
# Extension hook: commands beyond 00H-09H live in their own modules (e71_commands, e71_buffers)


class ExtensionResponse(Event, abc.ABC):
    """A response type defined by an extension module; it encodes itself (server side)."""

    __slots__ = ()
    #: the request's command code (the response subheader is ``command | 80H``)
    command: int

    @abc.abstractmethod
    def encode(self, code: Code) -> bytes: ...


class ExtensionRequest(E71Request, abc.ABC):
    """A request type defined by an extension module (client side): it encodes itself and
    sizes/decodes its own response, so the connection classes stay protocol-generic."""

    __slots__ = ()

    @abc.abstractmethod
    def encode(self, code: Code) -> bytes: ...

    @abc.abstractmethod
    def response_size(self, head: bytes, code: Code) -> int | None:
        """Wire length of the whole response that starts with ``head`` (at least its first 16
        bytes when available); ``None`` = more bytes needed. Raises RemoteProtocolError."""

    @abc.abstractmethod
    def decode_response(self, frame: bytes, code: Code) -> Response | ExtensionResponse:
        """Decode the complete response ``frame`` (5BH: with or without the trailing 00H)."""


#: server side: command -> decoder of the complete frame (raises Malformed with the end code)
ExtensionDecoders = Mapping[int, Callable[[bytes, Code, bool], ExtensionRequest]]


def encode_request(req: E71Request, code: Code) -> bytes:
    """Encode any request (§4.2, §7.3): the one path core and extension requests take.

    Raises :class:`LocalProtocolError` on misuse (counts outside the limits of §7.1, bad
    values, objects that are no E71 request).
    """
    if not isinstance(req, E71Request):
        cmd = getattr(req, "command", None)
        what = f"command {cmd:02X}H" if isinstance(cmd, int) else f"request {req!r}"
        raise LocalProtocolError(f"{what} is not implemented by this version of the E71 codec")
    return req.encode(code)


def encode_response(
    resp: Response | ExtensionResponse, code: Code, *, abnormal_trailer: bool = True
) -> bytes:
    """Encode a response (§4.3). 5BH gets abnormal code + 00H (A-series, §13 A3) unless
    ``abnormal_trailer`` is false (the Q-series form)."""
    if isinstance(resp, ExtensionResponse):
        return resp.encode(code)
    w = Writer(code is Code.ASCII)
    w.num((resp.command | 0x80) & 0xFF, 1)
    if isinstance(resp, ErrorResponse):
        w.num(resp.end_code, 1)
        if resp.end_code == 0x5B:
            w.num(resp.abnormal_code or 0, 1)
            if abnormal_trailer:
                w.num(0, 1)
        return w.getvalue()
    w.num(0, 1)
    if isinstance(resp, BitsResponse):
        w.raw(pack_bits(resp.values))
    elif isinstance(resp, WordsResponse):
        w.words(resp.values)
    return w.getvalue()
