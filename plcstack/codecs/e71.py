"""MELSEC A-series E71 "1E frame" codec: Sans-IO, both roles, binary and ASCII.

Reference: ``shared/specs/melsec-e71.md`` (section numbers below refer to it).

* :class:`ClientConnection` (alias ``E71ClientConnection``) is the partner (PC) side:
  ``send(request) -> bytes`` encodes a request and remembers it in a FIFO, because a 1E
  response can only be sized and decoded with the request it answers (§11.2);
  ``receive_data``/``next_event`` yield :class:`Ack`, :class:`BitsResponse`,
  :class:`WordsResponse` or :class:`ErrorResponse`. After a malformed response it is in the
  ERROR state and refuses further use.
* :class:`ServerConnection` (alias ``E71ServerConnection``) is the E71 side (the simulator): it
  frames requests of the WHOLE command table of §7.1 (00H-21H, 39H-3CH) plus 60H-62H by the
  length rules of §11.1, returns typed requests for the commands implemented here (00H-09H),
  :class:`OpaqueRequest` (the raw frame) for the other defined codes, and :class:`BadRequest`
  (with the end code a real E71 sends) for what cannot be parsed: it never raises on input.
  ``send(response) -> bytes`` encodes the answer.

The codec is split along its seams; this module holds the two connections and re-exports the
names of the others, so ``from plcstack.codecs.e71 import ...`` keeps working:

* :mod:`~plcstack.codecs.e71_wire` - field reader/writer of §3, ``Code``, bit packing
* :mod:`~plcstack.codecs.e71_devices` - devices, CPU groups, ranges, address parsing (§5)
* :mod:`~plcstack.codecs.e71_end_codes` - end codes and abnormal codes (§10)
* :mod:`~plcstack.codecs.e71_limits` - points per request and unit rules (§7.1, §7.3)
* :mod:`~plcstack.codecs.e71_events` - requests 00H-09H (each encodes itself), responses, the
  extension hook for :mod:`~plcstack.codecs.e71_commands`
* :mod:`~plcstack.codecs.e71_framing` - request sizing/decoding (§11.1) and the TCP (stream)
  and UDP (one message per datagram, §4.1) framers of both roles
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Callable
from typing import Final, cast

from plcstack.codecs._common import NEED_DATA, ErrorState, NeedData, ReceiveBuffer
from plcstack.codecs.e71_devices import (
    DEVICE_BY_CODE,
    SPECIAL_FIRST,
    SPECIAL_LAST,
    WIDEST_RANGES,
    CpuGroup,
    Device,
    DeviceRef,
    device_ranges,
    in_range,
    parse_address,
)
from plcstack.codecs.e71_end_codes import ABNORMAL_CODES, END_CODES
from plcstack.codecs.e71_events import (
    REQUEST_TYPES,
    Ack,
    BadRequest,
    BitsResponse,
    E71Request,
    ErrorResponse,
    ExtensionDecoders,
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
    encode_request,
    encode_response,
)
from plcstack.codecs.e71_framing import (
    REQUEST_RULES,
    StreamResponses,
    Transport,
    Unframed,
    decode_request,
    request_framer,
    response_framer,
    size_request,
)
from plcstack.codecs.e71_limits import command_limit, head_ok, limit_error, unit_error
from plcstack.codecs.e71_wire import (
    DEFAULT_PC,
    DEFAULT_TIMER,
    HEX,
    Code,
    Malformed,
    Reader,
    as_code,
    pack_bits,
    unpack_bits,
)
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "ABNORMAL_CODES",
    "DEFAULT_PC",
    "DEFAULT_TIMER",
    "DEVICE_BY_CODE",
    "END_CODES",
    "REQUEST_RULES",
    "REQUEST_TYPES",
    "SPECIAL_FIRST",
    "SPECIAL_LAST",
    "WIDEST_RANGES",
    "Ack",
    "BadRequest",
    "BitsResponse",
    "ClientConnection",
    "Code",
    "CpuGroup",
    "Device",
    "DeviceRef",
    "E71ClientConnection",
    "E71Request",
    "E71ServerConnection",
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
    "ServerConnection",
    "TestBits",
    "TestWords",
    "Transport",
    "WordsResponse",
    "WriteBits",
    "WriteWords",
    "command_limit",
    "decode_request",
    "device_ranges",
    "encode_request",
    "encode_response",
    "in_range",
    "limit_error",
    "pack_bits",
    "parse_address",
    "size_request",
    "unit_error",
    "unpack_bits",
]


class ServerConnection:
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
        self.code = as_code(code)
        self.transport = transport
        self.lower_ok = lower_ok
        self.abnormal_trailer = abnormal_trailer
        self.extensions = extensions
        self._framer = request_framer(transport, self.code, lower_ok)

    def receive_data(self, data: bytes) -> None:
        self._framer.feed(data)

    @property
    def buffered(self) -> int:
        """Bytes of an incomplete TCP request held (the simulator discards them after §13 A15)."""
        return self._framer.buffered

    def discard_partial(self) -> None:
        """Drop an incomplete request (the response monitoring time expired, error 71H)."""
        self._framer.discard_partial()

    def next_event(self) -> Request | OpaqueRequest | ExtensionRequest | BadRequest | NeedData:
        frame = self._framer.next_frame()
        if frame is NEED_DATA:
            return NEED_DATA
        if isinstance(frame, Unframed):
            return BadRequest(self._sub_of(frame.data), frame.end_code, None, frame.reason)
        try:
            return decode_request(
                frame, self.code, lower_ok=self.lower_ok, extensions=self.extensions
            )
        except Malformed as exc:
            return BadRequest(self._sub_of(frame), exc.end_code, exc.pc, exc.reason)

    def _sub_of(self, data: bytes) -> int:
        """The byte the E71 took as subheader (§2: it sets bit 7 of it in the answer)."""
        if self.code is Code.BINARY:
            return data[0] if data else 0
        if len(data) >= 2 and HEX.issuperset(data[:2]):
            return int(data[:2], 16)
        # [R] non-hex ASCII subheader: no byte to echo; answer FFH (7FH | 80H) with 54H.
        return 0x7F

    def send(self, response: Response | ExtensionResponse) -> bytes:
        return encode_response(response, self.code, abnormal_trailer=self.abnormal_trailer)


class ClientConnection(ErrorState):
    """The partner side of one connection: encode requests, decode their responses in order.

    Responses carry no sequence number, so each is sized and decoded with the request it answers
    (FIFO of pending requests, §11.2, App. C). The codec also remembers the last monitor
    registration acknowledged on this connection, to size 88H/89H responses.
    """

    def __init__(self, code: Code | str = Code.BINARY, *, transport: Transport = "tcp") -> None:
        self.code = as_code(code)
        self.transport = transport
        self._unit = 2 if self.code is Code.ASCII else 1
        self._framer = response_framer(transport, self.code)
        self._pending: deque[E71Request] = deque()
        framer = self._framer
        #: the TCP framer when the 01H fast path applies (binary), else None
        self._fast_stream: StreamResponses | None = (
            framer if self._unit == 1 and isinstance(framer, StreamResponses) else None
        )
        #: the stream framer's buffer, from which the fast path takes a normal 01H answer
        #: (an unused empty one for datagrams: ``_fast_stream`` is None then)
        if isinstance(framer, StreamResponses):
            self._fast_buffer = framer.buffer
            #: where received bytes go, bound once (the stream framer's feed is its buffer's)
            self._feed: Callable[[bytes], None] = framer.buffer.feed
        else:
            self._fast_buffer = ReceiveBuffer()
            self._feed = framer.feed
        #: the buffer's bytes: empty exactly when nothing is buffered (a truth test, no call)
        self._fast_held = self._fast_buffer.held
        #: the last ReadWords sent and its encoding (frozen: the same object encodes the same),
        #: and the size and word layout of its normal binary answer (``take_answer``)
        self._last_read: ReadWords | None = None
        self._last_bytes = b""
        self._last_size = 0
        self._last_unpack = _words_struct(1)
        #: points registered by the last acknowledged 06H / words by the last 07H
        self.monitor_bits: int | None = None
        self.monitor_words: int | None = None

    @property
    def pending(self) -> int:
        return len(self._pending)

    def send(self, request: Request | ExtensionRequest) -> bytes:
        if self.error is not None:
            self._check_usable()
        if request is self._last_read:  # only ever set by the fast path below: its bytes again
            self._pending.append(request)
            return self._last_bytes
        if type(request) is ReadWords and self._unit == 1:
            # The polling hot path: the checks of the general path (``_Header.encode``), inlined
            # over the fields a binary 01H frame holds, and one struct call. Anything it does
            # not accept takes the general path, which decides and words the refusal.
            last = self._last_read
            ref, count, pc, timer = request.ref, request.count, request.pc, request.timer
            if request is last or (
                # a new request with the very same field objects encodes the same bytes
                last is not None
                and ref is last.ref
                and count is last.count
                and pc is last.pc
                and timer is last.timer
            ):
                self._pending.append(request)
                return self._last_bytes
            if type(ref) is DeviceRef and type(count) is type(pc) is type(timer) is int:
                dev, number = ref.device, ref.number
                if (
                    1 <= count <= (_READ_WORDS_BIT_LIMIT if dev.is_bit else _READ_WORDS_LIMIT)
                    and 0 <= pc <= 0xFF
                    and 0 <= timer <= 0xFFFF
                    and type(number) is int
                    and 0 <= number <= 0xFFFFFFFF
                    and (not dev.is_bit or head_ok(ref))
                ):
                    data = _READ_FRAME.pack(0x01, pc, timer, number, dev.code, count & 0xFF, 0)
                    self._last_read, self._last_bytes = request, data
                    self._last_size, self._last_unpack = 2 + 2 * count, _words_struct(count)
                    self._pending.append(request)
                    return data
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
        if self.error is not None:
            self._check_usable()
        self._feed(data)

    def next_event(self) -> Response | ExtensionResponse | NeedData:
        """The response to the oldest pending request, or ``NEED_DATA``. A malformed response
        raises :class:`RemoteProtocolError` and leaves the connection in the ERROR state."""
        if self.error is not None:
            self._check_usable()
        pending = self._pending
        if (
            pending
            and (stream := self._fast_stream) is not None
            and type(req := pending[0]) is ReadWords
            and not stream.skip_trailer
        ):
            # 01H in binary over TCP: a normal answer (81H 00H + the words) is cut and decoded
            # at once; anything else (short, an error code, a trailer to skip) takes the
            # general path below, which decides exactly as before.
            n = req.count
            values = self._fast_buffer.take_unpacked(
                _NORMAL_01H, _WORDS_STRUCTS.get(n) or _words_struct(n)
            )
            if values is not None:
                pending.popleft()
                return WordsResponse(1, values)
        try:
            frame = self._framer.next_frame(pending[0] if pending else None, self._response_size)
            if frame is NEED_DATA:
                return NEED_DATA
            req = pending.popleft()
            if isinstance(req, ExtensionRequest):
                event = req.decode_response(frame, self.code)
            else:
                event = self._decode(cast("Request", req), frame)
        except RemoteProtocolError as exc:
            raise self._broken(exc) from None
        if isinstance(event, ErrorResponse) and event.end_code == 0x5B:
            self._framer.after_abnormal()
        return event

    def take_answer(self, data: bytes) -> WordsResponse | None:
        """The normal answer to the one pending 01H read, when ``data`` is exactly that answer
        and nothing is buffered before it (binary over TCP); else ``None`` and nothing taken.

        One step for what a poll does on every request: ``receive_data(data)``, then
        ``next_event()`` giving the words, then ``next_event()`` finding nothing after them.
        Where that would decide anything else (an error code, a short or long or split
        answer, a trailer to skip, several pending requests), the caller takes the general
        path with the same bytes (tests/test_fleet_paths.py compares both).
        """
        words = self.take_words(data)
        return None if words is None else WordsResponse(1, words)

    def take_words(self, data: bytes) -> tuple[int, ...] | None:
        """:meth:`take_answer`'s words alone: the same decision without the event object,
        for a caller that hands out only the words (the E71 client's prepared reads)."""
        stream = self._fast_stream
        pending = self._pending
        if (
            stream is None
            or len(pending) != 1
            # a 01H read encoded by ``send``'s fast path, which noted its answer's size and
            # layout (a polled read is always the same object)
            or pending[0] is not self._last_read
            or len(data) != self._last_size
            or not data.startswith(_NORMAL_01H)
            or self.error is not None
            or stream.skip_trailer
            or self._fast_held  # bytes buffered before this chunk: the general path
        ):
            return None
        pending.popleft()
        words: tuple[int, ...] = self._last_unpack.unpack_from(data, 2)
        return words

    # -- sizing and decoding ------------------------------------------------------------------
    def _response_size(self, req: E71Request, head: bytes) -> int | None:
        """Whole length of the response to ``req`` that starts with ``head`` (§11.2)."""
        if isinstance(req, ExtensionRequest):
            return req.response_size(head, self.code)
        core = cast("Request", req)
        u = self._unit
        _, end = self._head(head, core)
        if end == 0:
            return (2 + self._data_length(core)) * u
        if end == 0x5B:
            return 3 * u
        return 2 * u

    def _decode(self, req: Request, frame: bytes) -> Response:
        u = self._unit
        _, end = self._head(frame, req)
        if end == 0:
            return self._finish(req, frame[2 * u :])
        if end == 0x5B:
            return ErrorResponse(req.COMMAND, end, self._abnormal(frame[2 * u : 3 * u]))
        return ErrorResponse(req.COMMAND, end)

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
            return WordsResponse(1, _words_struct(req.count).unpack(body))
        if cls is WriteWords or cls is WriteBits:
            return Ack(req.COMMAND)  # a write's normal answer carries no data (_data_length 0)
        r = Reader(body, self.code is Code.ASCII)
        try:
            if isinstance(req, (ReadBits, MonitorBits)):
                n = req.count if isinstance(req, ReadBits) else self.monitor_bits or 0
                return BitsResponse(req.COMMAND, unpack_bits(r.raw((n + 1) // 2), n))
            if isinstance(req, (ReadWords, MonitorWords)):
                n = req.count if isinstance(req, ReadWords) else self.monitor_words or 0
                return WordsResponse(req.COMMAND, r.words(n))
        except Malformed as exc:
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
            r = Reader(data[: 2 * self._unit], self.code is Code.ASCII)
            sub, end = r.num(1), r.num(1)
        except Malformed:
            raise RemoteProtocolError(f"malformed response head {data[:4]!r}") from None
        if sub != req.COMMAND | 0x80:
            raise RemoteProtocolError(
                f"response subheader {sub:02X}H does not answer command {req.COMMAND:02X}H "
                f"(expected {req.COMMAND | 0x80:02X}H)"
            )
        return sub, end

    def _abnormal(self, data: bytes) -> int:
        try:
            return Reader(data, self.code is Code.ASCII).num(1)
        except Malformed:
            raise RemoteProtocolError(f"malformed abnormal code {data!r}") from None


_WORDS_STRUCTS: dict[int, struct.Struct] = {}
#: subheader 81H and end code 00H: the head of a normal answer to 01H (binary)
_NORMAL_01H: Final = b"\x81\x00"
#: most words one 01H reads (§7.1), of word devices and of bit devices (16 points a word)
_READ_WORDS_LIMIT: Final = command_limit(0x01, Device.D)
_READ_WORDS_BIT_LIMIT: Final = command_limit(0x01, Device.M)
#: subheader, PC number, timer, device number, device code, count, 00H of 00H-03H (binary)
_READ_FRAME: Final = struct.Struct("<BBHIHBB")


def _words_struct(count: int) -> struct.Struct:
    """``<countH``, compiled once per count (at most 256 of them)."""
    compiled = _WORDS_STRUCTS.get(count)
    if compiled is None:
        compiled = _WORDS_STRUCTS[count] = struct.Struct(f"<{count}H")
    return compiled


#: the names of the first versions, used throughout the package's E71 code
E71ClientConnection = ClientConnection
E71ServerConnection = ServerConnection
