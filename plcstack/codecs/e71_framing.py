"""E71 framing (spec §11): how long a message is, and the two ways bytes arrive.

* :func:`size_request` sizes a request of the WHOLE command table of §7.1 by the length rules of
  §11.1; :func:`decode_request` turns a complete frame into a typed request (E71 side).
* Responses have no length field: a response is sized with the request it answers (§11.2); the
  connection passes that knowledge in as a ``size_of(request, head)`` function.
* TCP is a byte stream: :class:`StreamRequests` / :class:`StreamResponses` cut frames from it.
  UDP carries exactly one message per datagram (§4.1): :class:`DatagramRequests` /
  :class:`DatagramResponses` check that each datagram is one whole frame. The connections in
  :mod:`plcstack.codecs.e71` hold one framer of each role and never ask which transport it is.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Final, Literal, NamedTuple, Protocol

from plcstack.codecs._common import NEED_DATA, NeedData, ReceiveBuffer
from plcstack.codecs.e71_devices import DeviceRef, decode_ref
from plcstack.codecs.e71_events import (
    E71Request,
    ExtensionDecoders,
    ExtensionRequest,
    MonitorBits,
    MonitorWords,
    OpaqueRequest,
    ReadBits,
    ReadWords,
    RegisterMonitorBits,
    RegisterMonitorWords,
    Request,
    TestBits,
    TestWords,
    WriteBits,
    WriteWords,
)
from plcstack.codecs.e71_wire import Code, Malformed, Reader, count_from, unpack_bits
from plcstack.errors import RemoteProtocolError

__all__ = [
    "COMMAND_NAMES",
    "REQUEST_RULES",
    "DatagramRequests",
    "DatagramResponses",
    "RequestFramer",
    "ResponseFramer",
    "StreamRequests",
    "StreamResponses",
    "Transport",
    "decode_request",
    "request_framer",
    "response_framer",
    "size_request",
]

Transport = Literal["tcp", "udp"]


# ---------------------------------------------------------------------------------------------
# Request sizing and decoding (§11.1)


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


#: What each defined subheader does (§2, §7.1 "Function"; §8, §9): the names the Wireshark
#: dissector shows (``plcstack wireshark``); one entry per key of REQUEST_RULES.
COMMAND_NAMES: Final[dict[int, str]] = {
    0x00: "batch read, bit units",
    0x01: "batch read, word units",
    0x02: "batch write, bit units",
    0x03: "batch write, word units",
    0x04: "test (random write), bit units",
    0x05: "test (random write), word units",
    0x06: "register monitor data, bit units",
    0x07: "register monitor data, word units",
    0x08: "monitor, bit units",
    0x09: "monitor, word units",
    0x0A: "read main sequence program / T,C set values",
    0x0B: "read sub sequence program / T,C set values",
    0x0C: "write main sequence program / T,C set values",
    0x0D: "write sub sequence program / T,C set values",
    0x0E: "special function module buffer memory batch read",
    0x0F: "special function module buffer memory batch write",
    0x10: "read parameters",
    0x11: "write parameters",
    0x12: "parameter analysis request",
    0x13: "remote RUN",
    0x14: "remote STOP",
    0x15: "read CPU model code",
    0x16: "loopback test",
    0x17: "extended file register batch read",
    0x18: "extended file register batch write",
    0x19: "extended file register test (random write)",
    0x1A: "extended file register monitor registration",
    0x1B: "extended file register monitor",
    0x1C: "comment memory read",
    0x1D: "comment memory write",
    0x1E: "microcomputer program read (MAIN)",
    0x1F: "microcomputer program read (SUB)",
    0x20: "microcomputer program write (MAIN)",
    0x21: "microcomputer program write (SUB)",
    0x39: "extended comment read",
    0x3A: "extended comment write",
    0x3B: "extended file register direct read",
    0x3C: "extended file register direct write",
    0x60: "fixed buffer data (with procedure)",
    0x61: "random access buffer read",
    0x62: "random access buffer write",
}

#: most words one 60H/62H message carries, by wire unit (1: binary, 2: ASCII; §1.5, §9)
_U16_MAX_WORDS: Final = {1: 1017, 2: 508}


class _Sized(NamedTuple):
    length: int  # in wire units (bytes; ASCII characters are bytes too)
    n: int


def _count_field(head: bytes, rule: _Rule, unit: int, lower_ok: bool) -> int | None:
    """Read the count field from the frame start; ``None`` = not enough bytes yet.
    Raises :class:`Malformed` for non-hex text or an impossible count."""
    assert rule.count_at is not None
    width = 2 if rule.kind in ("pts", "u16") else 1
    start = rule.count_at * unit
    if len(head) < start + width * unit:
        return None
    r = Reader(head[start : start + width * unit], unit == 2, lower_ok=lower_ok)
    if rule.kind == "u16":
        return r.num(2)
    low = r.num(1)
    if rule.kind == "byte":
        return low or 256
    fixed = r.num(1)
    # §13 A4: the fixed byte is 00H; [HSL] writes a 16-bit count, so 00 01 is accepted as 256.
    value = low | fixed << 8
    if value > 256:
        raise Malformed(0x57, f"point count field {value:#06x} is neither n,00 nor 00,01")
    return value or 256


def size_request(head: bytes, code: Code, *, lower_ok: bool = True) -> _Sized | None:
    """Length of the request starting at ``head`` (§11.1), ``None`` if more bytes are needed.

    Raises :class:`Malformed` (50H undefined subheader, 54H non-hex, 57H impossible count).
    """
    unit = 2 if code is Code.ASCII else 1
    if len(head) < unit:
        return None
    sub = Reader(head[:unit], unit == 2, lower_ok=lower_ok).num(1) if unit == 2 else head[0]
    rule = REQUEST_RULES.get(sub)
    if rule is None:
        raise Malformed(0x50, f"undefined subheader {sub:02X}H")
    if rule.count_at is None:
        return _Sized(rule.base * unit, 0)
    n = _count_field(head, rule, unit, lower_ok)
    if n is None:
        return None
    if rule.kind == "u16" and n > _U16_MAX_WORDS[unit]:
        # 60H/62H count their words in 16 bits, but no message carries more than 1017 words
        # (508 in ASCII; §1.5, §9): refused here, before up to 128 KiB are waited for.
        raise Malformed(0x52, f"{n} words for one message (at most {_U16_MAX_WORDS[unit]}, §1.5)")
    variable = (n + 1) // 2 if rule.packed else n
    return _Sized((rule.base + rule.per * variable) * unit, n)


def decode_request(
    frame: bytes,
    code: Code,
    *,
    lower_ok: bool = True,
    extensions: ExtensionDecoders | None = None,
) -> Request | OpaqueRequest | ExtensionRequest:
    """Decode one complete, correctly sized request frame (server side).

    Raises :class:`Malformed` with the E71's end code for what it would refuse to parse.
    """
    ascii_ = code is Code.ASCII
    r = Reader(frame, ascii_, lower_ok=lower_ok)
    cmd = r.num(1)
    if cmd not in (0x00, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x09):
        if extensions is not None and cmd in extensions:
            return extensions[cmd](frame, code, lower_ok)
        if cmd in REQUEST_RULES:
            return OpaqueRequest(cmd, frame)
        raise Malformed(0x50, f"undefined subheader {cmd:02X}H")
    pc = r.num(1)
    timer = r.num(2)
    hdr = {"pc": pc, "timer": timer}
    try:
        if cmd in (0x08, 0x09):
            return (MonitorBits if cmd == 0x08 else MonitorWords)(pc=pc, timer=timer)
        if cmd <= 0x03:
            ref = decode_ref(r)
            n = count_from(r)
            if cmd == 0x00:
                return ReadBits(ref, n, **hdr)
            if cmd == 0x01:
                return ReadWords(ref, n, **hdr)
            if cmd == 0x02:
                # §13 A8 decision: non-hex ASCII -> 54H (reader); otherwise the LSB decides.
                data = r.raw((n + 1) // 2)
                return WriteBits(ref, unpack_bits(data, n), **hdr)
            return WriteWords(ref, r.words(n), **hdr)
        n = count_from(r)
        if cmd == 0x04:
            bits: list[tuple[DeviceRef, bool]] = []
            for _ in range(n):
                ref = decode_ref(r)
                bits.append((ref, bool(r.num(1) & 1)))  # §13 A17: LSB decides
            return TestBits(tuple(bits), **hdr)
        if cmd == 0x05:
            words: list[tuple[DeviceRef, int]] = []
            for _ in range(n):
                ref = decode_ref(r)
                words.append((ref, r.num(2)))
            return TestWords(tuple(words), **hdr)
        refs = tuple(decode_ref(r) for _ in range(n))
        if cmd == 0x06:
            return RegisterMonitorBits(refs, **hdr)
        return RegisterMonitorWords(refs, **hdr)
    except Malformed as exc:
        exc.pc = pc
        raise


# ---------------------------------------------------------------------------------------------
# E71 side: cutting requests from the transport


class Unframed(NamedTuple):
    """Bytes that cannot be one request: the E71 answers ``end_code`` and drops them (§11.1)."""

    data: bytes
    end_code: int
    reason: str


class RequestFramer(Protocol):
    """Cuts complete request frames out of what the transport delivered (E71 side)."""

    def feed(self, data: bytes) -> None: ...

    def next_frame(self) -> bytes | Unframed | NeedData: ...

    @property
    def buffered(self) -> int: ...

    def discard_partial(self) -> None: ...


class StreamRequests:
    """TCP: frames sized from their fields (§11.1); several may be queued in the stream."""

    __slots__ = ("_buf", "code", "lower_ok")

    def __init__(self, code: Code, lower_ok: bool) -> None:
        self.code = code
        self.lower_ok = lower_ok
        self._buf = ReceiveBuffer()

    def feed(self, data: bytes) -> None:
        self._buf.feed(data)

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def discard_partial(self) -> None:
        self._buf.clear()

    def next_frame(self) -> bytes | Unframed | NeedData:
        buf = self._buf
        if not buf:
            return NEED_DATA
        try:
            sized = size_request(buf.peek(32), self.code, lower_ok=self.lower_ok)
        except Malformed as exc:
            # The frame cannot be sized: answer and drop everything buffered (§11.1).
            return Unframed(buf.take_all(), exc.end_code, exc.reason)
        if sized is None or len(buf) < sized.length:
            return NEED_DATA
        return buf.take(sized.length)


class DatagramRequests:
    """UDP: every datagram must be exactly one request (§4.1); nothing is held between them."""

    __slots__ = ("_datagrams", "code", "lower_ok")

    def __init__(self, code: Code, lower_ok: bool) -> None:
        self.code = code
        self.lower_ok = lower_ok
        self._datagrams: deque[bytes] = deque()

    def feed(self, data: bytes) -> None:
        self._datagrams.append(bytes(data))

    @property
    def buffered(self) -> int:
        return 0  # a datagram is whole or nothing: no partial request is ever held

    def discard_partial(self) -> None:
        pass

    def next_frame(self) -> bytes | Unframed | NeedData:
        if not self._datagrams:
            return NEED_DATA
        data = self._datagrams.popleft()
        try:
            sized = size_request(data, self.code, lower_ok=self.lower_ok)
        except Malformed as exc:
            return Unframed(data, exc.end_code, exc.reason)
        if sized is None or sized.length != len(data):
            return Unframed(
                data,
                0x57,
                f"datagram of {len(data)} bytes, frame says so "
                f"{'more' if sized is None else sized.length}",
            )
        return data


def request_framer(transport: Transport, code: Code, lower_ok: bool) -> RequestFramer:
    """The E71-side framer for ``transport``."""
    if transport == "udp":
        return DatagramRequests(code, lower_ok)
    return StreamRequests(code, lower_ok)


# ---------------------------------------------------------------------------------------------
# Partner side: cutting responses from the transport

#: ``size_of(request, head)``: whole response length for the request it answers, or ``None``
#: when more bytes are needed (raises RemoteProtocolError for a head that cannot answer it)
SizeOf = Callable[[E71Request, bytes], int | None]


class ResponseFramer(Protocol):
    """Cuts the response to the oldest pending request out of what the transport delivered."""

    def feed(self, data: bytes) -> None: ...

    def next_frame(self, request: E71Request | None, size_of: SizeOf) -> bytes | NeedData: ...

    def after_abnormal(self) -> None: ...

    def clear(self) -> None: ...


class StreamResponses:
    """TCP: responses cut from the stream by the size their request implies (§11.2)."""

    __slots__ = ("_buf", "_unit", "skip_trailer")

    def __init__(self, code: Code) -> None:
        self._unit = 2 if code is Code.ASCII else 1
        self._buf = ReceiveBuffer()
        #: a 5BH answer was taken and its optional 00H trailer not yet seen (§13 A3); the
        #: client codec's fast path reads it: while set, only :meth:`next_frame` may cut
        self.skip_trailer = False

    @property
    def buffer(self) -> ReceiveBuffer:
        """The stream's bytes. :meth:`feed` is exactly ``buffer.feed`` (the client codec binds
        that once), and a normal answer may be taken straight from it while
        :attr:`skip_trailer` is false (the fast path of :meth:`next_frame`)."""
        return self._buf

    def feed(self, data: bytes) -> None:
        self._buf.feed(data)

    def clear(self) -> None:
        self._buf.clear()

    def after_abnormal(self) -> None:
        """A 5BH answer was taken: a 00H trailer may follow it (§13 A3)."""
        self.skip_trailer = True

    def next_frame(self, request: E71Request | None, size_of: SizeOf) -> bytes | NeedData:
        buf = self._buf
        have = len(buf)
        if not have:
            return NEED_DATA
        u = self._unit
        if self.skip_trailer and have < u:
            return NEED_DATA  # half of an ASCII "00" trailer: wait for its second character
        if self.skip_trailer:
            # §13 A3: 5BH may be followed by 00H (A series) or not (Q series). No response
            # starts with 00H, so a leading 00H here is the trailer of the previous answer.
            if buf.peek(u) == (b"00" if u == 2 else b"\x00"):
                buf.take(u)
                have -= u
            self.skip_trailer = False
            if not have:
                return NEED_DATA
        if request is None:
            raise RemoteProtocolError(f"{have} byte(s) received without a pending request")
        if have < 2 * u:
            return NEED_DATA
        size = size_of(request, buf.peek(16))
        if size is None or have < size:
            return NEED_DATA
        return buf.take(size)


_FIVE_B: Final = (b"5B", b"5b", b"\x5b")


class DatagramResponses:
    """UDP: each datagram must be exactly the response to the oldest pending request (§4.1)."""

    __slots__ = ("_datagrams", "_unit")

    def __init__(self, code: Code) -> None:
        self._unit = 2 if code is Code.ASCII else 1
        self._datagrams: deque[bytes] = deque()

    def feed(self, data: bytes) -> None:
        self._datagrams.append(bytes(data))

    def clear(self) -> None:
        self._datagrams.clear()

    def after_abnormal(self) -> None:
        pass  # the trailer, if any, came inside the 5BH datagram

    def next_frame(self, request: E71Request | None, size_of: SizeOf) -> bytes | NeedData:
        if not self._datagrams:
            return NEED_DATA
        data = self._datagrams.popleft()
        if request is None:
            raise RemoteProtocolError(f"datagram of {len(data)} byte(s) without a pending request")
        u = self._unit
        if len(data) < 2 * u:
            raise RemoteProtocolError(f"datagram of {len(data)} byte(s) is too short")
        size = size_of(request, data)
        # a 5BH answer may carry the trailing 00H or not (§13 A3): one unit of slack
        slack = u if data[u : 2 * u] in _FIVE_B else 0
        if size is None or not size <= len(data) <= size + slack:
            raise RemoteProtocolError(
                f"{(request.COMMAND | 0x80) & 0xFF:02X}H datagram of {len(data)} byte(s), "
                f"expected {'more' if size is None else size}"
            )
        return data[:size]


def response_framer(transport: Transport, code: Code) -> ResponseFramer:
    """The partner-side framer for ``transport``."""
    if transport == "udp":
        return DatagramResponses(code)
    return StreamResponses(code)
