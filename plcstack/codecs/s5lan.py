"""Sans-IO codec for the Siemens S5-LAN-LINK 26-byte request block (spec part A), both roles.

The PC (client) sends a 26-byte block, followed by the data for a write; the module answers with a
block of the same layout, followed by the data for a successful read. There is no pipelining and
no transaction id: :class:`ClientConnection` allows one request in flight and checks the echoed
fields (including ``UserCode``, which the client uses as a request sequence number) so that a
reply can never be taken for the answer to another request. :class:`ServerConnection` is the
module side used by the simulator; it validates in the order of spec A.7 and tells its caller
which Err code to answer and whether the connection must be closed afterwards.

Data bytes are passed through as they travel: word data are low byte first on the wire (the module
swaps every word, A.6); :func:`swap_words` converts between wire and S5 (big-endian) order.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field
from typing import Final, Literal

from plcstack.codecs._common import NEED_DATA, Event, NeedData, ReceiveBuffer
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "AREA_LETTERS",
    "BLOCK_AREAS",
    "ERR_MEANINGS",
    "HEADER_BYTE_ORDER",
    "HEADER_LEN",
    "MAX_DATA_BYTES",
    "PLC_TYPE",
    "WORD_ONLY_AREAS",
    "BadRequest",
    "ClientConnection",
    "Header",
    "Request",
    "Response",
    "ServerConnection",
    "area_legal",
    "byte_order_hint",
    "err_meaning",
    "estimate_seconds",
    "response_timeout",
    "swap_words",
]

ByteOrder = Literal["little", "big"]

#: [R] Spec A.3 / D.A1: every WORD/integer field of the 26-byte header is little-endian (the module
#: was built for x86 PCs and already converts word data to "PC-friendly" order; the sibling Tani
#: header documents "INTEL format"). ``header_byte_order="big"`` exists for a peer that differs;
#: the codec never switches by itself.
HEADER_BYTE_ORDER: Final[ByteOrder] = "little"

HEADER_LEN: Final = 26
#: the module takes at most 2048 data bytes (Err 7); [R] D.A5: applied to reads as well
MAX_DATA_BYTES: Final = 2048
#: ``PLCType`` is the character '5' = 35h (D.A2); a lenient module also takes 05h
PLC_TYPE: Final = 0x35
PLC_TYPE_NUMERIC: Final = 0x05
#: firmware version * 100 the simulator reports (V1.04, as in the goldens of A.10)
DEFAULT_VERSION: Final = 104

READ_CMDS: Final = frozenset("Rr")
WRITE_CMDS: Final = frozenset("Ww")
DATA_TYPES: Final = {"B": 1, "W": 2}

#: ``DataArea`` letter -> meaning (spec A.4); E/I are inputs, A/O outputs, Z/C counters
AREA_LETTERS: Final[dict[str, str]] = {
    "M": "flags",
    "A": "outputs",
    "O": "outputs",
    "E": "inputs",
    "I": "inputs",
    "T": "timers",
    "Z": "counters",
    "C": "counters",
    "D": "data block DB",
    "X": "extended data block DX",
}
#: areas the module transfers only as words
WORD_ONLY_AREAS: Final = frozenset("TZCDX")
#: areas whose ``DBNo`` is evaluated
BLOCK_AREAS: Final = frozenset("DX")

#: ``Err`` values documented by the module (spec A.7, German original)
ERR_MEANINGS: Final[dict[int, str]] = {
    0: "success",
    2: "data area does not exist in the PLC (e.g. the requested DB does not exist)",
    3: "requested area too small (e.g. the DB is too short)",
    # a software module (plcstack gateway) has no access error in A.7 and answers 6 instead
    6: "the module detected an incorrect request format, or refused the request (a plcstack "
    "gateway refuses so a write outside its --writable)",
    7: "too much data sent to the module (max. 2048 bytes)",
    9: "timeout in the communication between the module and the PLC",
    10: "the module received too little data",
}

# Err values the simulator produces (names for readability)
ERR_OK: Final = 0
ERR_NO_AREA: Final = 2
ERR_AREA_TOO_SMALL: Final = 3
ERR_FORMAT: Final = 6
ERR_TOO_MUCH: Final = 7
ERR_PLC_TIMEOUT: Final = 9
ERR_TOO_LITTLE: Final = 10


def err_meaning(err: int) -> str:
    """Documented meaning of ``err``; undocumented values are ``unknown error n`` (A.7)."""
    return ERR_MEANINGS.get(err, f"unknown error {err}")


def area_legal(area: str, data_type: str) -> bool:
    """Whether the module accepts ``data_type`` ('B'/'W') for ``area`` (A.4)."""
    if area not in AREA_LETTERS or data_type not in DATA_TYPES:
        return False
    return data_type == "W" or area not in WORD_ONLY_AREAS


def estimate_seconds(n_bytes: int) -> float:
    """The module's documented answer time: 50 ms + 1.5 ms per data byte (A.8)."""
    return 0.050 + 0.0015 * n_bytes


def response_timeout(n_bytes: int, minimum: float = 2.0) -> float:
    """[R] A.8: ``max(2 * estimate + 1 s, minimum)``; 2048 bytes -> 7.2 s."""
    return max(2.0 * estimate_seconds(n_bytes) + 1.0, minimum)


def swap_words(data: bytes) -> bytes:
    """Swap the two bytes of every word: S5 (high byte first) <-> wire (low byte first)."""
    if len(data) % 2:
        raise ValueError("word data must have an even length")
    out = bytearray(len(data))
    out[0::2] = data[1::2]
    out[1::2] = data[0::2]
    return bytes(out)


#: the whole 26-byte block in one ``struct`` call (Err is signed, A.2)
_HEADER_LE: Final = struct.Struct("<BHBB3s3HhH4s4s")
_HEADER_BE: Final = struct.Struct(">BHBB3s3HhH4s4s")


@dataclass(frozen=True, slots=True)
class Header:
    """The 26-byte block, field by field (A.2). Letters are 1-character strings (latin-1)."""

    cmd: str
    data_type: str
    area: str
    db: int = 0
    start: int = 0
    count: int = 0
    err: int = 0
    version: int = 0
    user_code: bytes = bytes(4)
    plc_type: int = PLC_TYPE
    interface: int = 0
    plc_no: int = 0
    hd_len: int = HEADER_LEN
    reserved: bytes = bytes(4)

    @property
    def is_read(self) -> bool:
        return self.cmd in READ_CMDS

    @property
    def is_write(self) -> bool:
        return self.cmd in WRITE_CMDS

    @property
    def unit(self) -> int | None:
        """Bytes per unit of ``data_type`` (1 or 2), ``None`` for an unknown type."""
        return DATA_TYPES.get(self.data_type)

    @property
    def data_len(self) -> int | None:
        """Data bytes that go with this header, ``None`` if the data type is unknown."""
        unit = self.unit
        return None if unit is None else unit * self.count

    def encode(self, byte_order: ByteOrder = HEADER_BYTE_ORDER) -> bytes:
        """The 26 bytes; raises :class:`LocalProtocolError` for values that do not fit."""
        try:
            if len(self.user_code) != 4 or len(self.reserved) != 4:
                raise ValueError("user_code and reserved must be 4 bytes")
            return (_HEADER_LE if byte_order == "little" else _HEADER_BE).pack(
                self.plc_type,
                self.interface,
                self.plc_no,
                self.hd_len,
                (self.cmd + self.data_type + self.area).encode("latin-1"),
                self.db,
                self.start,
                self.count,
                self.err,
                self.version,
                self.user_code,
                self.reserved,
            )
        except (struct.error, ValueError, UnicodeEncodeError) as exc:
            raise LocalProtocolError(f"cannot encode S5-LAN header {self}: {exc}") from None

    @classmethod
    def decode(cls, data: bytes, byte_order: ByteOrder = HEADER_BYTE_ORDER) -> Header:
        """Parse exactly 26 bytes (no validation of the values; see the connections)."""
        if len(data) != HEADER_LEN:
            raise RemoteProtocolError(f"S5-LAN header needs {HEADER_LEN} bytes, got {len(data)}")
        layout = _HEADER_LE if byte_order == "little" else _HEADER_BE
        (plc_type, interface, plc_no, hd_len, letters, db, start, count, err, version, user_code,
         reserved) = layout.unpack(data)  # fmt: skip
        cmd, data_type, area = letters.decode("latin-1")
        return cls(cmd, data_type, area, db, start, count, err, version, user_code, plc_type,
                   interface, plc_no, hd_len, reserved)  # fmt: skip

    def response(self, err: int = 0, version: int = DEFAULT_VERSION) -> Header:
        """The module's answer to this request: the echo plus ``Err`` and ``VersionNo``."""
        return Header(
            cmd=self.cmd,
            data_type=self.data_type,
            area=self.area,
            db=self.db,
            start=self.start,
            count=self.count,
            err=err,
            version=version,
            user_code=self.user_code,
            plc_type=self.plc_type,
            interface=self.interface,
            plc_no=self.plc_no,
            hd_len=self.hd_len,
        )


# -- events ----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Request(Event):
    """A request block with its write data (client sends it; the server emits it when valid)."""

    header: Header
    data: bytes = b""

    @classmethod
    def read(
        cls,
        area: str,
        data_type: str,
        start: int,
        count: int,
        *,
        db: int = 0,
        user_code: bytes = bytes(4),
    ) -> Request:
        return cls(Header("R", data_type, area, db, start, count, user_code=user_code))

    @classmethod
    def write(
        cls,
        area: str,
        data_type: str,
        start: int,
        data: bytes,
        *,
        db: int = 0,
        user_code: bytes = bytes(4),
    ) -> Request:
        unit = DATA_TYPES.get(data_type, 1)
        return cls(
            Header("W", data_type, area, db, start, len(data) // unit, user_code=user_code), data
        )


@dataclass(frozen=True, slots=True)
class Response(Event):
    """The module's answer (client role): ``header.err`` and, for a successful read, the data."""

    header: Header
    data: bytes = b""
    #: names of echoed fields that differ from the request (only in lenient mode)
    echo_mismatch: tuple[str, ...] = field(default=())

    @property
    def err(self) -> int:
        return self.header.err

    @property
    def meaning(self) -> str:
        return err_meaning(self.header.err)


@dataclass(frozen=True, slots=True)
class BadRequest(Event):
    """Server role: answer ``header`` with ``err`` (no data); close afterwards if ``close``."""

    header: Header
    err: int
    reason: str
    close: bool = False


# -- client role -----------------------------------------------------------------------------
class _ClientState(enum.Enum):
    IDLE = "IDLE"
    WAIT_HEADER = "WAIT_HEADER"
    WAIT_DATA = "WAIT_DATA"
    ERROR = "ERROR"


_ECHOED = ("cmd", "data_type", "area", "db", "start", "count", "user_code")


class ClientConnection:
    """Client (PC) role: one request in flight, strict echo checks by default.

    ``strict=False`` accepts a reply whose echoed fields differ and lists them in
    :attr:`Response.echo_mismatch`; the byte counts are always taken from the request.
    """

    def __init__(self, *, header_byte_order: ByteOrder = HEADER_BYTE_ORDER, strict: bool = True):
        if header_byte_order not in ("little", "big"):
            raise LocalProtocolError(
                f"header_byte_order must be little or big, not {header_byte_order!r}"
            )
        self.byte_order: ByteOrder = header_byte_order
        self.strict = strict
        self.state = _ClientState.IDLE
        self.bytes_received = 0
        self._buf = ReceiveBuffer()
        self._request: Header | None = None
        self._request_head = b""
        self._reply_data = 0
        self._reply: Header | None = None
        self._mismatch: tuple[str, ...] = ()

    def send(self, request: Request) -> bytes:
        """Validate and encode ``request`` (header and write data in one piece, A1.5)."""
        if self.state is not _ClientState.IDLE:
            raise LocalProtocolError(
                f"S5-LAN allows one request at a time; the codec is in state {self.state.value}"
            )
        h = request.header
        is_read = h.cmd in READ_CMDS
        if not (is_read or h.cmd in WRITE_CMDS):
            raise LocalProtocolError(f"Cmd {h.cmd!r} is neither read (R/r) nor write (W/w)")
        if not area_legal(h.area, h.data_type):
            raise LocalProtocolError(
                f"data type {h.data_type!r} is not allowed for area {h.area!r} "
                "(T, Z/C, D and X are word-only)"
            )
        if not 1 <= h.count <= 0xFFFF:
            raise LocalProtocolError(f"count {h.count} outside 1..65535")
        n = h.data_len or 0
        if n > MAX_DATA_BYTES:
            raise LocalProtocolError(
                f"{n} data bytes exceed the module's limit of {MAX_DATA_BYTES}; split the request"
            )
        if not is_read and len(request.data) != n:
            raise LocalProtocolError(
                f"write of {h.count} {h.data_type} units needs {n} data bytes, "
                f"got {len(request.data)}"
            )
        if is_read and request.data:
            raise LocalProtocolError("a read request carries no data")
        head = h.encode(self.byte_order)
        self._request = h
        self._request_head = head
        self._reply_data = n if is_read else 0  # data bytes that follow a successful answer
        self.state = _ClientState.WAIT_HEADER
        return head + request.data

    def receive_data(self, data: bytes) -> None:
        self.bytes_received += len(data)
        self._buf.feed(data)

    def next_event(self) -> Response | NeedData:
        if self.state is _ClientState.ERROR:
            raise LocalProtocolError("the connection had a protocol error; open a new one")
        try:
            return self._next_event()
        except RemoteProtocolError:
            self.state = _ClientState.ERROR
            raise

    def _next_event(self) -> Response | NeedData:
        state, buf = self.state, self._buf
        if state is _ClientState.IDLE:
            if buf:
                raise RemoteProtocolError(
                    f"{len(buf)} unexpected byte(s) from the module with no request pending"
                )
            return NEED_DATA
        request = self._request
        assert request is not None
        if state is _ClientState.WAIT_HEADER:
            if len(buf) < HEADER_LEN:
                return NEED_DATA
            raw = buf.take(HEADER_LEN)
            reply = Header.decode(raw, self.byte_order)
            sent = self._request_head
            # Echoed fields are equal exactly when their bytes are (same byte order both ways):
            # Cmd/DataType/DataArea/DBNo/Start/Count at 5..13, UserCode at 18..21.
            if (
                raw[5:14] != sent[5:14]
                or raw[18:22] != sent[18:22]
                or reply.hd_len != HEADER_LEN
                or reply.plc_type not in (PLC_TYPE, PLC_TYPE_NUMERIC)
            ):
                self._check_reply(request, reply)
            self._reply = reply
            if reply.err != 0 or not self._reply_data:
                return self._finish(b"")
            self.state = _ClientState.WAIT_DATA
        assert self._reply is not None
        n = self._reply_data
        if len(buf) < n:
            return NEED_DATA
        return self._finish(buf.take(n))

    def _finish(self, data: bytes) -> Response:
        reply = self._reply
        assert reply is not None
        event = Response(reply, data, self._mismatch)
        self._request = self._reply = None
        self._mismatch = ()
        self.state = _ClientState.IDLE
        if self._buf:
            raise RemoteProtocolError(
                f"{len(self._buf)} byte(s) more than the answer to the request"
                + byte_order_hint(reply, self.byte_order)
            )
        return event

    def _check_reply(self, request: Header, reply: Header) -> None:
        if reply.hd_len != HEADER_LEN or reply.plc_type not in (PLC_TYPE, PLC_TYPE_NUMERIC):
            raise RemoteProtocolError(
                f"not an S5-LAN answer block (PLCType {reply.plc_type:#04x}, "
                f"HdLen {reply.hd_len}; expected 0x35 and 26)"
            )
        mismatch = tuple(f for f in _ECHOED if getattr(request, f) != getattr(reply, f))
        if not mismatch:
            return
        if self.strict:
            details = ", ".join(
                f"{f} {getattr(reply, f)!r} instead of {getattr(request, f)!r}" for f in mismatch
            )
            raise RemoteProtocolError(
                f"answer does not echo the request: {details}; it may be the answer to "
                "another request" + byte_order_hint(reply, self.byte_order)
            )
        self._mismatch = mismatch


def _swap16(value: int) -> int:
    return ((value & 0xFF) << 8) | (value >> 8)


def byte_order_hint(reply: Header, byte_order: ByteOrder = HEADER_BYTE_ORDER) -> str:
    """A diagnostic suffix when the module's own fields look byte-swapped, else ``""``.

    The echoed fields cannot show a byte-order mismatch (the module echoes our bytes), but
    ``VersionNo`` (e.g. 104 read as 6800h) and ``Err`` (2 read as 512) can. This only words a
    hint for an error message (A.3: never switch the byte order silently).
    """
    version_swapped = reply.version > 0xFF and reply.version & 0xFF == 0
    err = reply.err & 0xFFFF
    swapped_err = _swap16(err)
    err_swapped = err not in ERR_MEANINGS and swapped_err in ERR_MEANINGS and swapped_err != 0
    if not (version_swapped or err_swapped):
        return ""
    other = "big" if byte_order == "little" else "little"
    return (
        f" (VersionNo {reply.version:#06x} / Err {reply.err} look byte-swapped: the module may use "
        f"{other}-endian header fields; try the option header_byte_order={other})"
    )


# -- server (module) role ----------------------------------------------------------------------
class _ServerState(enum.Enum):
    WAIT_HEADER = "WAIT_HEADER"
    WAIT_WRITE_DATA = "WAIT_WRITE_DATA"
    DISCARD_WRITE_DATA = "DISCARD_WRITE_DATA"
    CLOSED = "CLOSED"


class ServerConnection:
    """Module role: parses request blocks and validates them in the order of spec A.7.

    :meth:`next_event` yields a valid :class:`Request` (the caller then checks the area, Err
    2/3, and answers with ``send(answer(request, err, data))``) or a :class:`BadRequest` carrying
    the Err code to answer. While write data are outstanding (:attr:`awaiting_data`), the caller
    runs the data timer and calls :meth:`data_timeout` when it expires (Err 10). After a
    ``BadRequest`` with ``close`` the connection must be closed; further input is ignored.
    """

    def __init__(
        self,
        *,
        header_byte_order: ByteOrder = HEADER_BYTE_ORDER,
        strict: bool = False,
        version: int = DEFAULT_VERSION,
    ) -> None:
        self.byte_order: ByteOrder = header_byte_order
        self.strict = strict
        self.version = version
        self.state = _ServerState.WAIT_HEADER
        self._buf = ReceiveBuffer()
        self._header: Header | None = None
        self._pending: BadRequest | None = None

    @property
    def awaiting_data(self) -> bool:
        """A write header arrived and its data are not complete yet (run the data timer)."""
        return self.state in (_ServerState.WAIT_WRITE_DATA, _ServerState.DISCARD_WRITE_DATA)

    @property
    def buffered(self) -> int:
        """Bytes received and not yet decoded (an incomplete header or data part)."""
        return len(self._buf)

    def receive_data(self, data: bytes) -> None:
        if self.state is not _ServerState.CLOSED:
            self._buf.feed(data)

    def next_event(self) -> Request | BadRequest | NeedData:
        if self.state is _ServerState.CLOSED:
            return NEED_DATA
        if self.state is _ServerState.WAIT_HEADER:
            if len(self._buf) < HEADER_LEN:
                return NEED_DATA
            header = Header.decode(self._buf.take(HEADER_LEN), self.byte_order)
            return self._validate(header)
        current = self._header
        assert current is not None
        n = current.data_len or 0
        if len(self._buf) < n:
            return NEED_DATA
        data = self._buf.take(n)
        self.state = _ServerState.WAIT_HEADER
        self._header = None
        if self._pending is not None:
            pending, self._pending = self._pending, None
            return pending
        return Request(current, data)

    def _validate(self, h: Header) -> Request | BadRequest | NeedData:
        plc_types = (PLC_TYPE,) if self.strict else (PLC_TYPE, PLC_TYPE_NUMERIC)
        # (1) structural: framing can no longer be trusted -> Err 6 and close
        if h.hd_len != HEADER_LEN or h.plc_type not in plc_types:
            return self._close(h, f"PLCType {h.plc_type:#04x} / HdLen {h.hd_len} not accepted")
        # [R] the spec is silent on the data length after an unknown Cmd; it may have been a write,
        # so we close as for an unknown data type on a write.
        if not (h.is_read or h.is_write):
            return self._close(h, f"unknown Cmd {h.cmd!r}")
        n = h.data_len
        if n is None:
            if h.is_write:
                return self._close(h, f"unknown DataType {h.data_type!r} on a write")
            return BadRequest(h, ERR_FORMAT, f"unknown DataType {h.data_type!r}")
        # (2) request format, (3) size; a write's data are consumed before the answer
        bad: BadRequest | None = None
        if h.area not in AREA_LETTERS:
            bad = BadRequest(h, ERR_FORMAT, f"unknown DataArea {h.area!r}")
        elif not area_legal(h.area, h.data_type):
            bad = BadRequest(h, ERR_FORMAT, f"DataType 'B' with word-only area {h.area!r}")
        elif h.count == 0:
            bad = BadRequest(h, ERR_FORMAT, "Count = 0")
        elif n > MAX_DATA_BYTES:
            bad = BadRequest(h, ERR_TOO_MUCH, f"{n} data bytes > {MAX_DATA_BYTES}")
        if not h.is_write or n == 0:
            return bad if bad is not None else Request(h)
        self._header = h
        self._pending = bad
        self.state = (
            _ServerState.WAIT_WRITE_DATA if bad is None else _ServerState.DISCARD_WRITE_DATA
        )
        return self.next_event()

    def _close(self, h: Header, reason: str) -> BadRequest:
        self.state = _ServerState.CLOSED
        self._buf.clear()
        return BadRequest(h, ERR_FORMAT, reason, close=True)

    def data_timeout(self) -> BadRequest:
        """The write data did not complete in time: drop what came and answer (Err 10, A.7 (4)).

        A write already refused for its format or size keeps that earlier Err (check order).
        """
        if not self.awaiting_data:
            raise LocalProtocolError("data_timeout() while no write data are outstanding")
        header = self._header
        assert header is not None
        self._buf.clear()
        self.state = _ServerState.WAIT_HEADER
        self._header = None
        pending, self._pending = self._pending, None
        if pending is not None:
            return pending
        return BadRequest(header, ERR_TOO_LITTLE, "write data incomplete at the data timeout")

    def answer(self, request: Header, err: int = ERR_OK, data: bytes = b"") -> Response:
        """The :class:`Response` event answering ``request`` (+ ``data`` for a successful read),
        checked; :meth:`send` encodes it."""
        if err == ERR_OK and request.is_read:
            if len(data) != (request.data_len or 0):
                raise LocalProtocolError(
                    f"read answer needs {request.data_len} data bytes, got {len(data)}"
                )
        elif data:
            raise LocalProtocolError("only a successful read answer carries data")
        return Response(request.response(err, self.version), data)

    def send(self, response: Response) -> bytes:
        """The answer block of ``response`` (built by :meth:`answer`), as every codec's
        ``send(event) -> bytes``."""
        return response.header.encode(self.byte_order) + response.data

    def send_response(self, request: Header, err: int = ERR_OK, data: bytes = b"") -> bytes:
        """``send(answer(request, err, data))`` in one call."""
        return self.send(self.answer(request, err, data))
