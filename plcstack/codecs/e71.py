"""MELSEC A-series E71 "1E frame" codec: Sans-IO, both roles, binary and ASCII.

Reference: ``shared/specs/melsec-e71.md`` (section numbers below refer to it).

* :class:`E71ClientConnection` is the partner (PC) side: ``send(request) -> bytes`` encodes a
  request and remembers it in a FIFO, because a 1E response can only be sized and decoded with
  the request it answers (§11.2); ``receive_data``/``next_event`` yield :class:`Ack`,
  :class:`BitsResponse`, :class:`WordsResponse` or :class:`ErrorResponse`.
* :class:`E71ServerConnection` is the E71 side (the simulator): it frames requests of the WHOLE
  command table of §7.1 (00H-21H, 39H-3CH) plus 60H-62H by the length rules of §11.1, returns typed
  requests for the commands implemented here (00H-09H), :class:`OpaqueRequest` (the raw frame) for
  the other defined codes, and :class:`BadRequest` (with the end code a real E71 sends) for what
  cannot be parsed. ``send(response) -> bytes`` encodes the answer.

Everything on the wire is a sequence of little-endian numeric fields or byte strings (§3). ASCII
prints each numeric field of width w as 2w upper-case hex digits, most significant first, and each
byte as 2 hex digits; so one field list serves both codes and they cannot drift apart. A device
designation is the 48-bit field ``code << 32 | number`` (§3 rule 3), bit data are the nibble-packed
bytes of §6.1 (whose hex rendering is the one-character-per-point ASCII form).

Transport framing: ``transport="tcp"`` treats input as a byte stream (frames sized from their
fields, several requests may be queued, FIFO); ``transport="udp"`` treats every ``receive_data``
call as exactly one datagram holding exactly one message (§4.1).
"""

from __future__ import annotations

import abc
import enum
import functools
import struct
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Final, Literal, NamedTuple

from plcstack.codecs._common import NEED_DATA, NeedData, ReceiveBuffer
from plcstack.errors import AddressError, LocalProtocolError, RemoteProtocolError

__all__ = [
    "ABNORMAL_CODES",
    "DEFAULT_PC",
    "DEFAULT_TIMER",
    "END_CODES",
    "Ack",
    "BadRequest",
    "BitsResponse",
    "Code",
    "CpuGroup",
    "Device",
    "DeviceRef",
    "E71ClientConnection",
    "E71ServerConnection",
    "ErrorResponse",
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
    "command_limit",
    "device_ranges",
    "limit_error",
    "parse_address",
    "unit_error",
]

#: PC number of the CPU in the station where the E71 is mounted (§4.2)
DEFAULT_PC: Final = 0xFF
#: ACPU monitoring timer, units of 250 ms; 000AH = 2.5 s, the value most tools send (§4.2)
DEFAULT_TIMER: Final = 0x000A


class Code(enum.Enum):
    """Module-wide code selection (DIP switch SW2, §0): never detected from the data (§11.4)."""

    BINARY = "binary"
    ASCII = "ascii"


# ---------------------------------------------------------------------------------------------
# Devices (§5)


class Device(enum.Enum):
    """A device of §5.1: its wire code, whether it is a bit device, the base of its numbers."""

    X = ("X", 0x5820, True, 16)
    Y = ("Y", 0x5920, True, 16)
    M = ("M", 0x4D20, True, 10)
    F = ("F", 0x4620, True, 10)
    B = ("B", 0x4220, True, 16)
    TS = ("TS", 0x5453, True, 10)
    TC = ("TC", 0x5443, True, 10)
    TN = ("TN", 0x544E, False, 10)
    CS = ("CS", 0x4353, True, 10)
    CC = ("CC", 0x4343, True, 10)
    CN = ("CN", 0x434E, False, 10)
    D = ("D", 0x4420, False, 10)
    W = ("W", 0x5720, False, 16)
    R = ("R", 0x5220, False, 10)

    def __init__(self, letters: str, code: int, is_bit: bool, base: int) -> None:
        self.letters = letters
        self.code = code
        self.is_bit = is_bit
        self.base = base

    def format_number(self, number: int) -> str:
        return f"{self.letters}{number:X}" if self.base == 16 else f"{self.letters}{number}"


DEVICE_BY_CODE: Final[dict[int, Device]] = {d.code: d for d in Device}
#: L (latch relay) and S (step relay) share the M address space on the A series (§5.1, §13 A9)
_ALIASES: Final = {"L": Device.M, "S": Device.M}
_NAMES: Final[dict[str, Device]] = {d.letters: d for d in Device} | _ALIASES

#: special relays / registers M9000-M9255, D9000-D9255 exist in every CPU group (§5.2)
SPECIAL_FIRST: Final = 9000
SPECIAL_LAST: Final = 9255


class CpuGroup(enum.Enum):
    """CPU groups of §5.2 (device ranges differ). VII = A3A/A3U/A4U/Q3A/Q4A."""

    I = "I"  # noqa: E741 - the spec's own name
    II = "II"
    III = "III"
    IV = "IV"
    V = "V"
    VI = "VI"
    VII = "VII"


_XY_LAST = {
    "I": 0xFF,
    "II": 0x1FF,
    "III": 0x3FF,
    "IV": 0x7FF,
    "V": 0x1FF,
    "VI": 0x3FF,
    "VII": 0x7FF,
}
_R_LAST = {"I": -1, "II": 4095, "III": 4095, "IV": 8191, "V": 8191, "VI": 8191, "VII": 8191}


def device_ranges(group: CpuGroup) -> dict[Device, int]:
    """Highest device number per device for ``group`` (§5.2); -1 = device absent.

    M and D additionally have 9000-9255 (special relays/registers) in every group.
    """
    big = group.value in ("V", "VI", "VII")
    xy = _XY_LAST[group.value]
    timers = 2047 if big else 255
    counters = 1023 if big else 255
    return {
        Device.X: xy,
        Device.Y: xy,
        Device.M: 8191 if big else 2047,
        Device.F: 2047 if big else 255,
        Device.B: 0xFFF if big else 0x3FF,
        Device.TS: timers,
        Device.TC: timers,
        Device.TN: timers,
        Device.CS: counters,
        Device.CC: counters,
        Device.CN: counters,
        Device.D: 6143 if big else 1023,
        Device.W: 0xFFF if big else 0x3FF,
        Device.R: _R_LAST[group.value],
    }


#: the widest range of any group: what a client accepts without knowing the CPU
WIDEST_RANGES: Final[dict[Device, int]] = {
    d: max(device_ranges(g)[d] for g in CpuGroup) for d in Device
}


def in_range(device: Device, first: int, count: int, last: dict[Device, int]) -> bool:
    """Whether ``first .. first+count-1`` lies in one valid range of ``device``."""
    end = first + count - 1
    if first >= 0 and end <= last[device]:
        return True
    return device in (Device.M, Device.D) and first >= SPECIAL_FIRST and end <= SPECIAL_LAST


@dataclass(frozen=True, slots=True)
class DeviceRef:
    """One device point, e.g. ``DeviceRef(Device.D, 100)``; ``str()`` gives ``D100``."""

    device: Device
    number: int

    def __str__(self) -> str:
        return self.device.format_number(self.number)


def parse_address(text: str, *, last: dict[Device, int] | None = None) -> DeviceRef:
    """``D100``, ``X1F`` (hex), ``M8000``, ``TN5``, ``L100`` (= M100) -> :class:`DeviceRef`.

    Numbers beyond the widest CPU group of §5.2 (or ``last``) are an :class:`AddressError`.
    """
    if last is None and isinstance(text, str):
        return _parse_cached(text)
    return _parse(text, last)


@functools.lru_cache(maxsize=4096)
def _parse_cached(text: str) -> DeviceRef:
    # pollers ask for the same few addresses over and over; DeviceRef is immutable
    return _parse(text, None)


def _parse(text: str, last: dict[Device, int] | None) -> DeviceRef:
    if not isinstance(text, str):
        raise AddressError(f"address {text!r} is not a string")
    upper = text.strip().upper()
    device: Device | None = None
    digits = ""
    for size in (2, 1):
        if len(upper) > size and upper[:size] in _NAMES:
            device, digits = _NAMES[upper[:size]], upper[size:]
            break
    if device is None:
        known = ", ".join([*(d.letters for d in Device), "L", "S"])
        raise AddressError(f"unknown MELSEC device in address {text!r}; known: {known}")
    try:
        if not digits or not all(c in "0123456789ABCDEF" for c in digits):
            raise ValueError
        number = int(digits, device.base)
    except ValueError:
        kind = "hexadecimal" if device.base == 16 else "decimal"
        raise AddressError(
            f"address {text!r}: {device.letters} takes a {kind} device number"
        ) from None
    if not in_range(device, number, 1, last or WIDEST_RANGES):
        raise AddressError(f"address {text!r}: device number out of range for {device.letters}")
    return DeviceRef(device, number)


# ---------------------------------------------------------------------------------------------
# End codes (§10)

END_CODES: Final[dict[int, str]] = {
    0x00: "normal completion",
    0x50: "subheader/command not one of the defined formats",
    0x51: "random access buffer start address outside 0-6143",
    0x52: "random access buffer start address + word count outside 0-6143, or too many words "
    "for one message; fixed buffer data count wrong",
    0x54: "ASCII data from the partner could not be converted (non-hex characters)",
    0x55: "write to the CPU refused: CPU in RUN and write during RUN not enabled (or a "
    "parameter/program write while in RUN)",
    0x56: "wrong device specification (unknown device code)",
    0x57: "number of points exceeds the per-request limit or the device range, command length "
    "wrong, write data count does not match, or monitor without prior registration",
    0x58: "head device number out of range, word device with a bit-unit command, or bit device "
    "head not a multiple of 16 in a word-unit command",
    0x59: "extended file register access on an A1(N) CPU",
    0x5B: "E71 and CPU cannot communicate / the CPU cannot process the request",
    0x60: "exchange between E71 and CPU exceeded the ACPU monitoring timer",
}

ABNORMAL_CODES: Final[dict[int, str]] = {
    0x10: "wrong PC number (no PLC with this number)",
    0x11: "mode error (E71 and CPU could not exchange data)",
    0x12: "special function module specification error",
    0x13: "program step number error",
    0x18: "remote RUN/STOP not possible (mode already changed remotely by another station)",
    0x20: "link error (the CPU given by the PC number cannot be accessed)",
    0x21: "special function module bus error",
}


# ---------------------------------------------------------------------------------------------
# Requests and responses (events)


@dataclass(frozen=True, slots=True)
class _Header:
    pc: int = field(default=DEFAULT_PC, kw_only=True)
    timer: int = field(default=DEFAULT_TIMER, kw_only=True)


@dataclass(frozen=True, slots=True)
class ReadBits(_Header):
    """00H: batch read in bit units (bit devices), 1-256 points."""

    COMMAND: ClassVar[int] = 0x00
    ref: DeviceRef
    count: int


@dataclass(frozen=True, slots=True)
class ReadWords(_Header):
    """01H: batch read in word units; for bit devices ``count`` is in words of 16 points."""

    COMMAND: ClassVar[int] = 0x01
    ref: DeviceRef
    count: int


@dataclass(frozen=True, slots=True)
class WriteBits(_Header):
    """02H: batch write in bit units."""

    COMMAND: ClassVar[int] = 0x02
    ref: DeviceRef
    values: tuple[bool, ...]


@dataclass(frozen=True, slots=True)
class WriteWords(_Header):
    """03H: batch write in word units (bit devices: 16 points per word, bit 0 = head)."""

    COMMAND: ClassVar[int] = 0x03
    ref: DeviceRef
    values: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class TestBits(_Header):
    """04H: test (random write) in bit units: ``(point, state)`` pairs."""

    COMMAND: ClassVar[int] = 0x04
    __test__: ClassVar[bool] = False  # not a pytest class
    points: tuple[tuple[DeviceRef, bool], ...]


@dataclass(frozen=True, slots=True)
class TestWords(_Header):
    """05H: test (random write) in word units: ``(head, word)`` pairs."""

    COMMAND: ClassVar[int] = 0x05
    __test__: ClassVar[bool] = False  # not a pytest class
    points: tuple[tuple[DeviceRef, int], ...]


@dataclass(frozen=True, slots=True)
class RegisterMonitorBits(_Header):
    """06H: register bit points for monitoring with 08H."""

    COMMAND: ClassVar[int] = 0x06
    refs: tuple[DeviceRef, ...]


@dataclass(frozen=True, slots=True)
class RegisterMonitorWords(_Header):
    """07H: register words (word devices, or 16-point heads of bit devices) for 09H."""

    COMMAND: ClassVar[int] = 0x07
    refs: tuple[DeviceRef, ...]


@dataclass(frozen=True, slots=True)
class MonitorBits(_Header):
    """08H: read the points registered by 06H."""

    COMMAND: ClassVar[int] = 0x08


@dataclass(frozen=True, slots=True)
class MonitorWords(_Header):
    """09H: read the words registered by 07H."""

    COMMAND: ClassVar[int] = 0x09


@dataclass(frozen=True, slots=True)
class OpaqueRequest:
    """A defined command this version does not interpret (server side): the whole raw frame.

    ``frame`` is exactly the bytes received (ASCII text for ASCII), so a later version can parse
    it; the framing (its length) is already right, so the stream stays in step.
    """

    command: int
    frame: bytes


@dataclass(frozen=True, slots=True)
class BadRequest:
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


@dataclass(frozen=True, slots=True)
class Ack:
    """Normal completion without data (82H-87H)."""

    command: int


@dataclass(frozen=True, slots=True)
class BitsResponse:
    """Normal completion with bit data in bit units (80H, 88H)."""

    command: int
    values: tuple[bool, ...]


@dataclass(frozen=True, slots=True)
class WordsResponse:
    """Normal completion with words (81H, 89H)."""

    command: int
    values: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class ErrorResponse:
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


class ExtensionResponse(abc.ABC):
    """A response type defined by an extension module; it encodes itself (server side)."""

    __slots__ = ()
    #: the request's command code (the response subheader is ``command | 80H``)
    command: int

    @abc.abstractmethod
    def encode(self, code: Code) -> bytes: ...


class ExtensionRequest(abc.ABC):
    """A request type defined by an extension module (client side): it encodes itself and
    sizes/decodes its own response, so the connection classes below stay protocol-generic."""

    __slots__ = ()
    COMMAND: ClassVar[int]

    @abc.abstractmethod
    def encode(self, code: Code) -> bytes: ...

    @abc.abstractmethod
    def response_size(self, head: bytes, code: Code) -> int | None:
        """Wire length of the whole response that starts with ``head`` (at least its first 16
        bytes when available); ``None`` = more bytes needed. Raises RemoteProtocolError."""

    @abc.abstractmethod
    def decode_response(self, frame: bytes, code: Code) -> Response | ExtensionResponse:
        """Decode the complete response ``frame`` (5BH: with or without the trailing 00H)."""


#: server side: command -> decoder of the complete frame (raises _Malformed with the end code)
ExtensionDecoders = Mapping[int, Callable[[bytes, Code, bool], ExtensionRequest]]


# ---------------------------------------------------------------------------------------------
# Limits (§7.1) shared by the client (checked before sending) and the simulator (end codes)

_BIT_ONLY: Final = frozenset({0x00, 0x02, 0x04, 0x06})


def command_limit(command: int, device: Device | None) -> int:
    """Most points per request (§7.1). Word-unit commands on bit devices count words.

    For 05H/07H with a mix of devices the smaller (entry) limit applies: 40 / 20 entries.
    [R] decision (§7.1 footnote): the "X counts twice" rule for non-AnA CPUs is not applied;
    the client cannot know the CPU and the simulator defaults to an AnA group (VII). A count
    field of 00H means 256 and is refused with 57H where the limit is lower (§13 A5).
    """
    if device is not None and device.is_bit:
        return _LIMITS_BIT[command]
    return _LIMITS_WORD[command]


_LIMITS_WORD: Final = {0x00: 256, 0x01: 256, 0x02: 256, 0x03: 256, 0x04: 80, 0x05: 40, 0x06: 40}
_LIMITS_WORD[0x07] = 20
_LIMITS_BIT: Final = {**_LIMITS_WORD, 0x01: 128, 0x03: 40}


def _head_ok(ref: DeviceRef) -> bool:
    if not ref.device.is_bit:
        return True
    base = SPECIAL_FIRST if ref.device is Device.M and ref.number >= SPECIAL_FIRST else 0
    return (ref.number - base) % 16 == 0


def _refs(req: Request) -> list[DeviceRef]:
    if isinstance(req, (ReadBits, ReadWords, WriteBits, WriteWords)):
        return [req.ref]
    if isinstance(req, (TestBits, TestWords)):
        return [p[0] for p in req.points]
    if isinstance(req, (RegisterMonitorBits, RegisterMonitorWords)):
        return list(req.refs)
    return []


def unit_error(req: Request) -> str | None:
    """End code 58H cases that need no CPU knowledge: word device in a bit-unit command, bit
    device head not a multiple of 16 in a word-unit command (§7.3, §10.1)."""
    bit_unit = req.COMMAND in _BIT_ONLY
    for ref in _refs(req):
        if bit_unit and not ref.device.is_bit:
            return f"{ref} is a word device; command {req.COMMAND:02X}H works in bit units"
        if not bit_unit and not _head_ok(ref):
            return f"{ref}: a bit device in word units needs a head that is a multiple of 16"
    return None


def point_count(req: Request) -> int:
    """The value of the request's point-count field (0 for 08H/09H)."""
    if isinstance(req, (ReadBits, ReadWords)):
        return req.count
    if isinstance(req, (WriteBits, WriteWords)):
        return len(req.values)
    if isinstance(req, (TestBits, TestWords)):
        return len(req.points)
    if isinstance(req, (RegisterMonitorBits, RegisterMonitorWords)):
        return len(req.refs)
    return 0


def limit_error(req: Request) -> str | None:
    """End code 57H for a count outside 1..limit of §7.1, else ``None``."""
    if isinstance(req, (MonitorBits, MonitorWords)):
        return None
    n = point_count(req)
    refs = _refs(req)
    device = refs[0].device if len(refs) == 1 or req.COMMAND < 0x04 else None
    limit = command_limit(req.COMMAND, device)
    if not 1 <= n <= limit:
        unit = (
            "words" if device is not None and device.is_bit and req.COMMAND in (1, 3) else "points"
        )
        return f"command {req.COMMAND:02X}H takes 1-{limit} {unit}, got {n}"
    return None


# ---------------------------------------------------------------------------------------------
# Field encoding (§3)

_HEX: Final = frozenset(b"0123456789ABCDEFabcdef")
_HEX_UPPER: Final = frozenset(b"0123456789ABCDEF")


def _dev_value(ref: DeviceRef) -> int:
    return ref.device.code << 32 | ref.number


def pack_bits(values: Sequence[bool]) -> bytes:
    """§6.1: two points per byte, first point in the high nibble, odd count padded with 0."""
    out = bytearray((len(values) + 1) // 2)
    for i, v in enumerate(values):
        if v:
            out[i >> 1] |= 0x01 if i & 1 else 0x10
    return bytes(out)


def unpack_bits(data: bytes, count: int) -> tuple[bool, ...]:
    """Inverse of :func:`pack_bits`; only the nibble's least significant bit counts (§6.1)."""
    return tuple(bool(data[i >> 1] & (0x01 if i & 1 else 0x10)) for i in range(count))


class _Writer:
    """Collects fields in wire order; renders binary (LE) or ASCII (hex, MSD first)."""

    __slots__ = ("ascii", "parts")

    def __init__(self, ascii_: bool) -> None:
        self.ascii = ascii_
        self.parts: list[bytes] = []

    def num(self, value: int, width: int) -> None:
        if self.ascii:
            self.parts.append(b"%0*X" % (2 * width, value))
        else:
            self.parts.append(value.to_bytes(width, "little"))

    def words(self, values: Sequence[int]) -> None:
        if self.ascii:
            self.parts.append(struct.pack(f">{len(values)}H", *values).hex().upper().encode())
        else:
            self.parts.append(struct.pack(f"<{len(values)}H", *values))

    def raw(self, data: bytes) -> None:
        self.parts.append(data.hex().upper().encode() if self.ascii else data)

    def getvalue(self) -> bytes:
        return b"".join(self.parts)


class _Malformed(Exception):
    """Internal: the reader hit non-hex text (ASCII) or ran out of data."""

    def __init__(self, end_code: int, reason: str) -> None:
        super().__init__(reason)
        self.end_code = end_code
        self.reason = reason
        self.pc: int | None = None


class _Reader:
    """Reads fields from one complete frame (binary bytes or ASCII text)."""

    __slots__ = ("ascii", "data", "hexset", "pos")

    def __init__(self, data: bytes, ascii_: bool, *, lower_ok: bool = True) -> None:
        self.data = data
        self.ascii = ascii_
        self.pos = 0
        self.hexset = _HEX if lower_ok else _HEX_UPPER

    def _text(self, nchars: int) -> bytes:
        end = self.pos + nchars
        if end > len(self.data):
            raise _Malformed(0x57, "message shorter than its fields")
        chunk = self.data[self.pos : end]
        if not self.hexset.issuperset(chunk):
            raise _Malformed(0x54, f"non-hex characters {chunk!r}")
        self.pos = end
        return chunk

    def num(self, width: int) -> int:
        if self.ascii:
            return int(self._text(2 * width), 16)
        end = self.pos + width
        if end > len(self.data):
            raise _Malformed(0x57, "message shorter than its fields")
        value = int.from_bytes(self.data[self.pos : end], "little")
        self.pos = end
        return value

    def raw(self, nbytes: int) -> bytes:
        if self.ascii:
            return bytes.fromhex(self._text(2 * nbytes).decode())
        end = self.pos + nbytes
        if end > len(self.data):
            raise _Malformed(0x57, "message shorter than its fields")
        out = self.data[self.pos : end]
        self.pos = end
        return out

    def words(self, count: int) -> tuple[int, ...]:
        if self.ascii:
            text = self._text(4 * count)
            return struct.unpack(f">{count}H", bytes.fromhex(text.decode()))
        end = self.pos + 2 * count
        if end > len(self.data):
            raise _Malformed(0x57, "message shorter than its fields")
        values = struct.unpack_from(f"<{count}H", self.data, self.pos)
        self.pos = end
        return values


def _check_ref(ref: DeviceRef) -> None:
    if not isinstance(ref, DeviceRef) or not 0 <= ref.number <= 0xFFFFFFFF:
        raise LocalProtocolError(f"not a device reference: {ref!r}")


def _check_word(value: int) -> None:
    if not isinstance(value, int) or not 0 <= value <= 0xFFFF:
        raise LocalProtocolError(f"word value {value!r} outside 0..65535")


_READ_FRAME: Final = struct.Struct("<BBHIHBB")
#: what ``_check_word`` accepts as a type (``bool`` is an ``int``)
_INT_OR_BOOL: Final = frozenset({int, bool})


def encode_request(req: Request, code: Code) -> bytes:
    """Encode one implemented request (§4.2, §7.3); raises :class:`LocalProtocolError` on misuse
    (counts outside the limits of §7.1, bad values, unknown request types)."""
    cls = type(req)
    if code is Code.BINARY and (cls is ReadWords or cls is ReadBits):
        # The polling hot path: the same checks as below, inlined, and one struct call.
        assert isinstance(req, (ReadBits, ReadWords))
        ref, count = req.ref, req.count
        dev = ref.device
        if (
            1 <= count <= command_limit(cls.COMMAND, dev)
            and (dev.is_bit if cls is ReadBits else _head_ok(ref))
            and 0 <= req.pc <= 0xFF
            and 0 <= req.timer <= 0xFFFF
            and 0 <= ref.number <= 0xFFFFFFFF
        ):
            return _READ_FRAME.pack(
                cls.COMMAND, req.pc, req.timer, ref.number, dev.code, count & 0xFF, 0
            )
    if code is Code.BINARY and cls is WriteWords:
        # The write hot path: the checks of the general path below, with the per-value
        # ``_check_word`` loop replaced by one type check and ``struct``'s own range check.
        assert isinstance(req, WriteWords)
        ref, values = req.ref, req.values
        n = len(values)
        if (
            type(ref) is DeviceRef
            and 1 <= n <= command_limit(0x03, ref.device)
            and _head_ok(ref)
            and 0 <= req.pc <= 0xFF
            and 0 <= req.timer <= 0xFFFF
            and 0 <= ref.number <= 0xFFFFFFFF
            and set(map(type, values)) <= _INT_OR_BOOL
        ):
            try:
                data = struct.pack(f"<{n}H", *values)
            except struct.error:
                pass  # a value out of range: the general path names it
            else:
                head = _READ_FRAME.pack(
                    0x03, req.pc, req.timer, ref.number, ref.device.code, n & 0xFF, 0
                )
                return head + data
    if not isinstance(req, REQUEST_TYPES):
        cmd = getattr(req, "command", None)
        what = f"command {cmd:02X}H" if isinstance(cmd, int) else f"request {req!r}"
        raise LocalProtocolError(f"{what} is not implemented by this version of the E71 codec")
    if not (0 <= req.pc <= 0xFF and 0 <= req.timer <= 0xFFFF):
        raise LocalProtocolError(f"PC number {req.pc!r} or monitoring timer {req.timer!r} invalid")
    for ref in _refs(req):
        _check_ref(ref)
    problem = limit_error(req) or unit_error(req)
    if problem is not None:
        raise LocalProtocolError(problem)
    n = point_count(req) & 0xFF  # 256 -> 00H (§6.4)
    w = _Writer(code is Code.ASCII)
    w.num(req.COMMAND, 1)
    w.num(req.pc, 1)
    w.num(req.timer, 2)
    if isinstance(req, (ReadBits, ReadWords)):
        w.num(_dev_value(req.ref), 6)
        w.num(n, 1)
        w.num(0, 1)
    elif isinstance(req, WriteBits):
        w.num(_dev_value(req.ref), 6)
        w.num(n, 1)
        w.num(0, 1)
        w.raw(pack_bits(req.values))
    elif isinstance(req, WriteWords):
        for v in req.values:
            _check_word(v)
        w.num(_dev_value(req.ref), 6)
        w.num(n, 1)
        w.num(0, 1)
        w.words(req.values)
    elif isinstance(req, TestBits):
        w.num(n, 1)
        w.num(0, 1)
        for ref, state in req.points:
            w.num(_dev_value(ref), 6)
            w.num(1 if state else 0, 1)
    elif isinstance(req, TestWords):
        w.num(n, 1)
        w.num(0, 1)
        for ref, value in req.points:
            _check_word(value)
            w.num(_dev_value(ref), 6)
            w.num(value, 2)
    elif isinstance(req, (RegisterMonitorBits, RegisterMonitorWords)):
        w.num(n, 1)
        w.num(0, 1)
        for ref in req.refs:
            w.num(_dev_value(ref), 6)
    return w.getvalue()


def encode_response(
    resp: Response | ExtensionResponse, code: Code, *, abnormal_trailer: bool = True
) -> bytes:
    """Encode a response (§4.3). 5BH gets abnormal code + 00H (A-series, §13 A3) unless
    ``abnormal_trailer`` is false (the Q-series form)."""
    if isinstance(resp, ExtensionResponse):
        return resp.encode(code)
    w = _Writer(code is Code.ASCII)
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


# ---------------------------------------------------------------------------------------------
# Request framing for the whole command table (§11.1)


class _Rule(NamedTuple):
    """Binary length = ``base + per * f(n)``; ASCII length is twice that (every field doubles).

    ``count_at`` = binary offset of the count field; ``kind``: "pts" = 1 byte + fixed 00H
    (00H = 256), "byte" = 1 byte (00H = 256), "u16" = 2 bytes LE taken as is; ``packed`` = the
    variable part is ceil(n/2) (nibble-packed bits) instead of n.
    """

    base: int
    count_at: int | None = None
    kind: Literal["pts", "byte", "u16"] = "pts"
    per: int = 0
    packed: bool = False


#: Every defined subheader (§2, §7.1). Entries marked [R] follow the reconstructed layout of §7.8.
#: [R] decision (§2): 22H-38H and everything else not listed here are undefined -> 50H.
REQUEST_RULES: Final[dict[int, _Rule]] = {
    0x00: _Rule(12),
    0x01: _Rule(12),
    0x02: _Rule(12, 10, "pts", 1, packed=True),
    0x03: _Rule(12, 10, "pts", 2),
    0x04: _Rule(6, 4, "pts", 7),
    0x05: _Rule(6, 4, "pts", 8),
    0x06: _Rule(6, 4, "pts", 6),
    0x07: _Rule(6, 4, "pts", 6),
    0x08: _Rule(4),
    0x09: _Rule(4),
    0x0A: _Rule(8),  # [R]
    0x0B: _Rule(8),  # [R]
    0x0C: _Rule(8, 6, "pts", 2),  # [R]
    0x0D: _Rule(8, 6, "pts", 2),  # [R]
    0x0E: _Rule(10),
    0x0F: _Rule(10, 7, "byte", 1),
    0x10: _Rule(9),  # [R]
    0x11: _Rule(9, 7, "pts", 1),  # [R]
    0x12: _Rule(4),
    0x13: _Rule(4),
    0x14: _Rule(4),
    0x15: _Rule(4),
    0x16: _Rule(5, 4, "byte", 1),
    0x17: _Rule(14),
    0x18: _Rule(14, 12, "pts", 2),
    0x19: _Rule(6, 4, "pts", 10),
    0x1A: _Rule(6, 4, "pts", 8),
    0x1B: _Rule(4),
    0x1C: _Rule(8),  # [R]
    0x1D: _Rule(8, 6, "pts", 1),  # [R]
    0x1E: _Rule(8),  # [R]
    0x1F: _Rule(8),  # [R]
    0x20: _Rule(8, 6, "pts", 1),  # [R]
    0x21: _Rule(8, 6, "pts", 1),  # [R]
    0x39: _Rule(8),  # [R]
    0x3A: _Rule(8, 6, "pts", 1),  # [R]
    0x3B: _Rule(12),
    0x3C: _Rule(12, 10, "pts", 2),
    0x60: _Rule(4, 2, "u16", 2),
    0x61: _Rule(6),
    0x62: _Rule(6, 4, "u16", 2),
}


class _Sized(NamedTuple):
    length: int  # in wire units (bytes; ASCII characters are bytes too)
    n: int


def _count_field(head: bytes, rule: _Rule, unit: int, lower_ok: bool) -> int | None:
    """Read the count field from the frame start; ``None`` = not enough bytes yet.
    Raises :class:`_Malformed` for non-hex text or an impossible count."""
    assert rule.count_at is not None
    width = 2 if rule.kind in ("pts", "u16") else 1
    start = rule.count_at * unit
    if len(head) < start + width * unit:
        return None
    r = _Reader(head[start : start + width * unit], unit == 2, lower_ok=lower_ok)
    if rule.kind == "u16":
        return r.num(2)
    low = r.num(1)
    if rule.kind == "byte":
        return low or 256
    fixed = r.num(1)
    # §13 A4: the fixed byte is 00H; [HSL] writes a 16-bit count, so 00 01 is accepted as 256.
    value = low | fixed << 8
    if value > 256:
        raise _Malformed(0x57, f"point count field {value:#06x} is neither n,00 nor 00,01")
    return value or 256


def size_request(head: bytes, code: Code, *, lower_ok: bool = True) -> _Sized | None:
    """Length of the request starting at ``head`` (§11.1), ``None`` if more bytes are needed.

    Raises :class:`_Malformed` (50H undefined subheader, 54H non-hex, 57H impossible count).
    """
    unit = 2 if code is Code.ASCII else 1
    if len(head) < unit:
        return None
    sub = _Reader(head[:unit], unit == 2, lower_ok=lower_ok).num(1) if unit == 2 else head[0]
    rule = REQUEST_RULES.get(sub)
    if rule is None:
        raise _Malformed(0x50, f"undefined subheader {sub:02X}H")
    if rule.count_at is None:
        return _Sized(rule.base * unit, 0)
    n = _count_field(head, rule, unit, lower_ok)
    if n is None:
        return None
    variable = (n + 1) // 2 if rule.packed else n
    return _Sized((rule.base + rule.per * variable) * unit, n)


def _decode_ref(r: _Reader) -> DeviceRef:
    value = r.num(6)
    dcode, number = value >> 32, value & 0xFFFFFFFF
    device = DEVICE_BY_CODE.get(dcode)
    if device is None:
        raise _Malformed(0x56, f"unknown device code {dcode:04X}H")
    return DeviceRef(device, number)


def decode_request(
    frame: bytes,
    code: Code,
    *,
    lower_ok: bool = True,
    extensions: ExtensionDecoders | None = None,
) -> Request | OpaqueRequest | ExtensionRequest:
    """Decode one complete, correctly sized request frame (server side).

    Raises :class:`_Malformed` with the E71's end code for what it would refuse to parse.
    """
    ascii_ = code is Code.ASCII
    r = _Reader(frame, ascii_, lower_ok=lower_ok)
    cmd = r.num(1)
    if cmd not in (0x00, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x09):
        if extensions is not None and cmd in extensions:
            return extensions[cmd](frame, code, lower_ok)
        if cmd in REQUEST_RULES:
            return OpaqueRequest(cmd, frame)
        raise _Malformed(0x50, f"undefined subheader {cmd:02X}H")
    pc = r.num(1)
    timer = r.num(2)
    hdr = {"pc": pc, "timer": timer}
    try:
        if cmd in (0x08, 0x09):
            return (MonitorBits if cmd == 0x08 else MonitorWords)(pc=pc, timer=timer)
        if cmd <= 0x03:
            ref = _decode_ref(r)
            n = _count_from(r)
            if cmd == 0x00:
                return ReadBits(ref, n, **hdr)
            if cmd == 0x01:
                return ReadWords(ref, n, **hdr)
            if cmd == 0x02:
                # §13 A8 decision: non-hex ASCII -> 54H (reader); otherwise the LSB decides.
                data = r.raw((n + 1) // 2)
                return WriteBits(ref, unpack_bits(data, n), **hdr)
            return WriteWords(ref, r.words(n), **hdr)
        n = _count_from(r)
        if cmd == 0x04:
            bits: list[tuple[DeviceRef, bool]] = []
            for _ in range(n):
                ref = _decode_ref(r)
                bits.append((ref, bool(r.num(1) & 1)))  # §13 A17: LSB decides
            return TestBits(tuple(bits), **hdr)
        if cmd == 0x05:
            words: list[tuple[DeviceRef, int]] = []
            for _ in range(n):
                ref = _decode_ref(r)
                words.append((ref, r.num(2)))
            return TestWords(tuple(words), **hdr)
        refs = tuple(_decode_ref(r) for _ in range(n))
        if cmd == 0x06:
            return RegisterMonitorBits(refs, **hdr)
        return RegisterMonitorWords(refs, **hdr)
    except _Malformed as exc:
        exc.pc = pc
        raise


def _count_from(r: _Reader) -> int:
    low = r.num(1)
    fixed = r.num(1)
    value = low | fixed << 8
    if value > 256:
        raise _Malformed(0x57, f"point count field {value:#06x} is neither n,00 nor 00,01")
    return value or 256


# ---------------------------------------------------------------------------------------------
# Connections

Transport = Literal["tcp", "udp"]


def _code(code: Code | str) -> Code:
    try:
        return code if isinstance(code, Code) else Code(code)
    except ValueError:
        raise LocalProtocolError(f"code must be 'binary' or 'ascii', not {code!r}") from None


class E71ServerConnection:
    """The E71 side of one connection (TCP stream or UDP datagrams).

    ``next_event()`` returns a typed request, an :class:`OpaqueRequest`, a :class:`BadRequest`
    (answer it with ``ErrorResponse(bad.command, bad.end_code)``) or ``NEED_DATA``. Never raises
    on input: the simulator must answer everything and keep the connection (§10).
    ``lower_ok=False`` is the strict mode of §13 A7 (lower-case hex answered with 54H).
    ``extensions`` maps further commands to decoders (``plcstack.codecs.e71_commands``); their
    frames come out as :class:`ExtensionRequest` objects instead of :class:`OpaqueRequest`.
    """

    def __init__(
        self,
        code: Code | str = Code.BINARY,
        *,
        transport: Transport = "tcp",
        lower_ok: bool = True,
        abnormal_trailer: bool = True,
        extensions: ExtensionDecoders | None = None,
    ) -> None:
        self.code = _code(code)
        self.transport = transport
        self.lower_ok = lower_ok
        self.abnormal_trailer = abnormal_trailer
        self.extensions = extensions
        self._buf = ReceiveBuffer()
        self._datagrams: deque[bytes] = deque()

    def receive_data(self, data: bytes) -> None:
        if self.transport == "udp":
            self._datagrams.append(bytes(data))
        else:
            self._buf.feed(data)

    @property
    def buffered(self) -> int:
        """Bytes of an incomplete TCP request held (the simulator discards them after §13 A15)."""
        return len(self._buf)

    def discard_partial(self) -> None:
        """Drop an incomplete request (the response monitoring time expired, error 71H)."""
        self._buf.clear()

    def next_event(self) -> Request | OpaqueRequest | ExtensionRequest | BadRequest | NeedData:
        if self.transport == "udp":
            if not self._datagrams:
                return NEED_DATA
            return self._one_datagram(self._datagrams.popleft())
        buf = self._buf
        if not buf:
            return NEED_DATA
        try:
            sized = size_request(buf.peek(32), self.code, lower_ok=self.lower_ok)
        except _Malformed as exc:
            # The frame cannot be sized: answer and drop everything buffered (§11.1).
            head = buf.take_all()
            return BadRequest(self._sub_of(head), exc.end_code, None, exc.reason)
        if sized is None or len(buf) < sized.length:
            return NEED_DATA
        return self._parse(buf.take(sized.length))

    def _one_datagram(self, data: bytes) -> Request | OpaqueRequest | ExtensionRequest | BadRequest:
        try:
            sized = size_request(data, self.code, lower_ok=self.lower_ok)
        except _Malformed as exc:
            return BadRequest(self._sub_of(data), exc.end_code, None, exc.reason)
        if sized is None or sized.length != len(data):
            return BadRequest(
                self._sub_of(data),
                0x57,
                None,
                f"datagram of {len(data)} bytes, frame says so "
                f"{'more' if sized is None else sized.length}",
            )
        return self._parse(data)

    def _parse(self, frame: bytes) -> Request | OpaqueRequest | ExtensionRequest | BadRequest:
        try:
            return decode_request(
                frame, self.code, lower_ok=self.lower_ok, extensions=self.extensions
            )
        except _Malformed as exc:
            return BadRequest(self._sub_of(frame), exc.end_code, exc.pc, exc.reason)

    def _sub_of(self, data: bytes) -> int:
        """The byte the E71 took as subheader (§2: it sets bit 7 of it in the answer)."""
        if self.code is Code.BINARY:
            return data[0] if data else 0
        if len(data) >= 2 and _HEX.issuperset(data[:2]):
            return int(data[:2], 16)
        # [R] non-hex ASCII subheader: no byte to echo; answer FFH (7FH | 80H) with 54H.
        return 0x7F

    def send(self, response: Response | ExtensionResponse) -> bytes:
        return encode_response(response, self.code, abnormal_trailer=self.abnormal_trailer)


class E71ClientConnection:
    """The partner side of one connection: encode requests, decode their responses in order.

    Responses carry no sequence number, so each is sized and decoded with the request it answers
    (FIFO of pending requests, §11.2, App. C). The codec also remembers the last monitor
    registration acknowledged on this connection, to size 88H/89H responses.
    """

    def __init__(self, code: Code | str = Code.BINARY, *, transport: Transport = "tcp") -> None:
        self.code = _code(code)
        self.transport = transport
        self._unit = 2 if self.code is Code.ASCII else 1
        self._buf = ReceiveBuffer()
        self._datagrams: deque[bytes] = deque()
        self._pending: deque[Request | ExtensionRequest] = deque()
        self._skip_trailer = False
        #: points registered by the last acknowledged 06H / words by the last 07H
        self.monitor_bits: int | None = None
        self.monitor_words: int | None = None

    @property
    def pending(self) -> int:
        return len(self._pending)

    def send(self, request: Request | ExtensionRequest) -> bytes:
        if isinstance(request, ExtensionRequest):
            ext = request.encode(self.code)
            self._pending.append(request)
            return ext
        if isinstance(request, MonitorBits) and self.monitor_bits is None:
            raise LocalProtocolError("monitor 08H before a bit registration (06H) was acknowledged")
        if isinstance(request, MonitorWords) and self.monitor_words is None:
            raise LocalProtocolError(
                "monitor 09H before a word registration (07H) was acknowledged"
            )
        data = encode_request(request, self.code)
        self._pending.append(request)
        return data

    def receive_data(self, data: bytes) -> None:
        if self.transport == "udp":
            self._datagrams.append(bytes(data))
        else:
            self._buf.feed(data)

    # -- decoding -----------------------------------------------------------------------------
    def _data_length(self, req: Request) -> int:
        """Binary length of the data after subheader + end code of a normal response (§11.2)."""
        cls = type(req)
        if type(req) is ReadWords:
            return 2 * req.count
        if cls is WriteWords or cls is WriteBits:
            return 0
        if isinstance(req, ReadBits):
            return (req.count + 1) // 2
        if isinstance(req, ReadWords):
            return 2 * req.count
        if isinstance(req, MonitorBits):
            return ((self.monitor_bits or 0) + 1) // 2
        if isinstance(req, MonitorWords):
            return 2 * (self.monitor_words or 0)
        return 0

    def _finish(self, req: Request, body: bytes) -> Response:
        cls = type(req)
        if type(req) is ReadWords and self._unit == 1:
            return WordsResponse(1, struct.unpack(f"<{req.count}H", body))
        if cls is WriteWords or cls is WriteBits:
            return Ack(req.COMMAND)  # a write's normal answer carries no data (_data_length 0)
        r = _Reader(body, self.code is Code.ASCII)
        try:
            if isinstance(req, (ReadBits, MonitorBits)):
                n = req.count if isinstance(req, ReadBits) else self.monitor_bits or 0
                return BitsResponse(req.COMMAND, unpack_bits(r.raw((n + 1) // 2), n))
            if isinstance(req, (ReadWords, MonitorWords)):
                n = req.count if isinstance(req, ReadWords) else self.monitor_words or 0
                return WordsResponse(req.COMMAND, r.words(n))
        except _Malformed as exc:
            raise RemoteProtocolError(
                f"malformed {req.COMMAND | 0x80:02X}H response: {exc}"
            ) from None
        if isinstance(req, RegisterMonitorBits):
            self.monitor_bits, self.monitor_words = len(req.refs), None
        elif isinstance(req, RegisterMonitorWords):
            self.monitor_bits, self.monitor_words = None, len(req.refs)
        return Ack(req.COMMAND)

    def _head(self, data: bytes, req: Request) -> tuple[int, int]:
        """Subheader check and end code from the first 2 units (§11.3)."""
        if self._unit == 1:
            sub, end = data[0], data[1]
            if sub == req.COMMAND | 0x80:
                return sub, end
        try:
            r = _Reader(data[: 2 * self._unit], self.code is Code.ASCII)
            sub, end = r.num(1), r.num(1)
        except _Malformed:
            raise RemoteProtocolError(f"malformed response head {data[:4]!r}") from None
        if sub != req.COMMAND | 0x80:
            raise RemoteProtocolError(
                f"response subheader {sub:02X}H does not answer command {req.COMMAND:02X}H "
                f"(expected {req.COMMAND | 0x80:02X}H)"
            )
        return sub, end

    def _abnormal(self, data: bytes) -> int:
        try:
            return _Reader(data, self.code is Code.ASCII).num(1)
        except _Malformed:
            raise RemoteProtocolError(f"malformed abnormal code {data!r}") from None

    def next_event(self) -> Response | ExtensionResponse | NeedData:
        if self.transport == "udp":
            return self._next_datagram()
        buf = self._buf
        have = len(buf)
        if not have:
            return NEED_DATA
        u = self._unit
        if self._skip_trailer and have < u:
            return NEED_DATA  # half of an ASCII "00" trailer: wait for its second character
        if self._skip_trailer:
            # §13 A3: 5BH may be followed by 00H (A series) or not (Q series). No response
            # starts with 00H, so a leading 00H here is the trailer of the previous answer.
            if buf.peek(u) == (b"00" if u == 2 else b"\x00"):
                buf.take(u)
                have -= u
            self._skip_trailer = False
            if not have:
                return NEED_DATA
        if not self._pending:
            raise RemoteProtocolError(f"{have} byte(s) received without a pending request")
        if have < 2 * u:
            return NEED_DATA
        req = self._pending[0]
        if isinstance(req, ExtensionRequest):
            size = req.response_size(buf.peek(16), self.code)
            if size is None or len(buf) < size:
                return NEED_DATA
            frame = buf.take(size)
            self._pending.popleft()
            event = req.decode_response(frame, self.code)
            self._skip_trailer = isinstance(event, ErrorResponse) and event.end_code == 0x5B
            return event
        _, end = self._head(buf.peek(2 * u), req)
        if end == 0:
            total = (2 + self._data_length(req)) * u
            if have < total:
                return NEED_DATA
            frame = buf.take(total)
            self._pending.popleft()
            return self._finish(req, frame[2 * u :])
        if end == 0x5B:
            if have < 3 * u:
                return NEED_DATA
            frame = buf.take(3 * u)
            self._pending.popleft()
            self._skip_trailer = True
            return ErrorResponse(req.COMMAND, end, self._abnormal(frame[2 * u :]))
        buf.take(2 * u)
        self._pending.popleft()
        return ErrorResponse(req.COMMAND, end)

    def _next_datagram(self) -> Response | ExtensionResponse | NeedData:
        if not self._datagrams:
            return NEED_DATA
        data = self._datagrams.popleft()
        if not self._pending:
            raise RemoteProtocolError(f"datagram of {len(data)} byte(s) without a pending request")
        u = self._unit
        if len(data) < 2 * u:
            raise RemoteProtocolError(f"datagram of {len(data)} byte(s) is too short")
        req = self._pending.popleft()
        if isinstance(req, ExtensionRequest):
            size = req.response_size(data, self.code)
            # a 5BH answer may carry the trailing 00H or not (§13 A3): one unit of slack
            slack = u if data[u : 2 * u] in (b"5B", b"5b", b"\x5b") else 0
            if size is None or not size <= len(data) <= size + slack:
                raise RemoteProtocolError(
                    f"{req.COMMAND | 0x80:02X}H datagram of {len(data)} byte(s), "
                    f"expected {'more' if size is None else size}"
                )
            return req.decode_response(data[:size], self.code)
        _, end = self._head(data, req)
        if end == 0:
            total = (2 + self._data_length(req)) * u
            if len(data) != total:
                raise RemoteProtocolError(
                    f"{req.COMMAND | 0x80:02X}H datagram of {len(data)} byte(s), expected {total}"
                )
            return self._finish(req, data[2 * u :])
        if end == 0x5B:
            if len(data) not in (3 * u, 4 * u):
                raise RemoteProtocolError(f"5BH datagram of {len(data)} byte(s)")
            return ErrorResponse(req.COMMAND, end, self._abnormal(data[2 * u : 3 * u]))
        if len(data) != 2 * u:
            raise RemoteProtocolError(f"error datagram of {len(data)} byte(s), expected {2 * u}")
        return ErrorResponse(req.COMMAND, end)

    def forget_pending(self) -> None:
        """Drop pending requests (after the connection was closed)."""
        self._pending.clear()
        self._buf.clear()
        self._datagrams.clear()
