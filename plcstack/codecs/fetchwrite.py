"""Siemens S5 FETCH/WRITE: the 16-byte ``'S' '5'`` header, spec part C.6-C.8. Sans-IO, both roles.

A job is one request and one acknowledgement; there is no transaction id, so a client has at most
one job outstanding. Two framings (C.7):

* ``raw``: plain TCP. Boundaries follow from the header: a WRITE request carries ``length`` units of
  data, a FETCH acknowledgement with error 0 carries the data *of the outstanding request*.
* ``mk``: every request and every acknowledgement is one MK message (:mod:`plcstack.codecs.mk`);
  boundaries come from the continuation bit and are cross-checked against the header.

:class:`ClientConnection` is the PC side, :class:`ServerConnection` the CP/module side.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import Final, Literal

from plcstack.codecs._common import NEED_DATA, ErrorState, Event, NeedData, ReceiveBuffer
from plcstack.codecs.mk import LifeAck, Message, MkConnection
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "ERROR_MEANINGS",
    "HEADER_LEN",
    "BadRequest",
    "ClientConnection",
    "FetchRequest",
    "FetchResponse",
    "Framing",
    "OpCode",
    "Org",
    "ServerConnection",
    "WriteRequest",
    "WriteResponse",
    "data_bytes",
    "encode_ack",
    "encode_request",
    "error_meaning",
    "parse_ack_header",
    "parse_request_header",
    "unit_size",
]

HEADER_LEN: Final = 16
SYSTEM_ID: Final = b"S5"

Framing = Literal["raw", "mk"]
DbStartUnit = Literal["word", "byte"]


class OpCode(enum.IntEnum):
    """Byte 5 of the header (C.6.1/C.6.2)."""

    WRITE_REQUEST = 0x03
    WRITE_RESPONSE = 0x04
    FETCH_REQUEST = 0x05
    FETCH_RESPONSE = 0x06


class Org(enum.IntEnum):
    """ORG IDs (memory areas) of C.6.3."""

    DB = 0x01  # data block DBNR, start = DW number, words
    MB = 0x02  # flags, bytes
    EB = 0x03  # process image of inputs, bytes
    AB = 0x04  # process image of outputs, bytes
    PB = 0x05  # peripheral I/O bytes
    ZB = 0x06  # counters, one word each
    TB = 0x07  # timers, one word each
    BS = 0x08  # system data words
    AS = 0x09  # absolute addresses, words
    DX = 0x0A  # extended data block DBNR, words
    DE = 0x10  # DB in external memory, words
    QB = 0x11  # extended I/O, bytes


#: bytes per length unit of each ORG ID; words for 01/06/07/08/09/0A/10, bytes for the rest.
# [R] C.6.3 / D.C5: units of 08, 09, 0A, 10, 11 are our decision (the sources give only names).
_UNIT: Final[dict[int, int]] = {
    Org.DB: 2,
    Org.MB: 1,
    Org.EB: 1,
    Org.AB: 1,
    Org.PB: 1,
    Org.ZB: 2,
    Org.TB: 2,
    Org.BS: 2,
    Org.AS: 2,
    Org.DX: 2,
    Org.DE: 2,
    Org.QB: 1,
}

#: error field values and their meaning (C.6.4); clients accept any value
ERROR_MEANINGS: Final[dict[int, str]] = {
    0x00: "no error",
    0x01: "area cannot be read/written; wrong ORG format (bad ORG ID or length)",
    0x02: "requested block or area does not exist",
    0x03: "requested block or area too small",
    0x04: "timeout (QVZ) in the PLC",
    0xFF: "error, reason unknown",
}


def error_meaning(code: int) -> str:
    return ERROR_MEANINGS.get(code, "undocumented error code")


def unit_size(org: int) -> int:
    """Bytes per length unit of ``org``; :class:`LocalProtocolError` for an unknown ORG ID."""
    try:
        return _UNIT[org]
    except KeyError:
        raise LocalProtocolError(f"unknown ORG ID {org:#04x}") from None


def data_bytes(org: int, length: int) -> int:
    """Data byte count of a job of ``length`` units of ``org``."""
    return unit_size(org) * length


# -- jobs and acknowledgements --------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FetchRequest(Event):
    """FETCH ``length`` units of ``org`` (block ``db`` for DB/DX/DE) from ``start``."""

    org: int
    db: int
    start: int
    length: int


@dataclass(frozen=True, slots=True)
class WriteRequest(Event):
    """WRITE ``data`` (``length`` units of ``org``) at ``start``."""

    org: int
    db: int
    start: int
    length: int
    data: bytes

    @classmethod
    def of(cls, org: int, db: int, start: int, data: bytes) -> WriteRequest:
        """Build with ``length`` computed from ``data`` and the ORG's unit."""
        size = unit_size(org)
        if len(data) % size:
            raise LocalProtocolError(f"{len(data)} data bytes are not whole units of {size}")
        return cls(org, db, start, len(data) // size, data)


@dataclass(frozen=True, slots=True)
class FetchResponse(Event):
    """The FETCH acknowledgement: ``error`` (0 = ok) and, only when 0, the data."""

    error: int
    data: bytes = b""


@dataclass(frozen=True, slots=True)
class WriteResponse(Event):
    """The WRITE acknowledgement: ``error`` (0 = written)."""

    error: int


@dataclass(frozen=True, slots=True)
class BadRequest(Event):
    """Server side: a well-formed header the module must refuse with ``error`` (C.6.4/C.6.5).

    ``close`` is set when the stream cannot be resynchronised (raw framing, WRITE with an unknown
    ORG ID: the amount of data that follows is unknown), so the server answers and then closes.
    """

    opcode: int
    org: int
    db: int
    start: int
    length: int
    error: int
    reason: str
    close: bool = False


Request = FetchRequest | WriteRequest
Response = FetchResponse | WriteResponse


# -- header encoding / decoding ------------------------------------------------------------

_REQ = struct.Struct(">2sBBBBBBBBHHBB")
_ACK = struct.Struct(">2sBBBBBBBBB5s")


def encode_request(request: Request) -> bytes:
    """The 16-byte request header, plus the data for a WRITE (C.6.1)."""
    if not 0 <= request.db <= 0xFF:
        raise LocalProtocolError(f"DBNR {request.db} outside 0..255")
    if not 0 <= request.start <= 0xFFFF or not 0 <= request.length <= 0xFFFF:
        raise LocalProtocolError(
            f"start {request.start} / length {request.length} do not fit 16 bits"
        )
    if not 0 <= request.org <= 0xFF:
        raise LocalProtocolError(f"ORG ID {request.org} outside 0..255")
    if isinstance(request, WriteRequest):
        opcode, data = OpCode.WRITE_REQUEST, request.data
        if len(data) != data_bytes(request.org, request.length):
            raise LocalProtocolError(
                f"WRITE of {request.length} units of ORG {request.org:#04x} needs "
                f"{data_bytes(request.org, request.length)} data bytes, got {len(data)}"
            )
    else:
        opcode, data = OpCode.FETCH_REQUEST, b""
    header = _REQ.pack(
        SYSTEM_ID,
        HEADER_LEN,
        0x01,
        0x03,
        opcode,
        0x03,
        0x08,
        request.org,
        request.db,
        request.start,
        request.length,
        0xFF,
        0x02,
    )
    return header + data


def encode_ack(opcode: int, error: int, data: bytes = b"") -> bytes:
    """The 16-byte acknowledgement (C.6.2) with ``opcode`` 04 or 06, plus FETCH data."""
    if opcode not in (OpCode.WRITE_RESPONSE, OpCode.FETCH_RESPONSE):
        raise LocalProtocolError(f"{opcode:#04x} is not an acknowledgement opcode")
    if not 0 <= error <= 0xFF:
        raise LocalProtocolError(f"error field {error} outside 0..255")
    if data and (error or opcode != OpCode.FETCH_RESPONSE):
        raise LocalProtocolError("only a FETCH acknowledgement with error 0 carries data")
    return _ACK.pack(SYSTEM_ID, HEADER_LEN, 0x01, 0x03, opcode, 0x0F, 0x03, error, 0xFF, 0x07,
                     bytes(5)) + data  # fmt: skip


def parse_request_header(header: bytes) -> tuple[int, int, int, int, int]:
    """``(opcode, org, db, start, length)`` of a request header (malformed: RemoteProtocolError)."""
    if len(header) != HEADER_LEN:
        raise RemoteProtocolError(f"FETCH/WRITE request header of {len(header)} bytes")
    (sysid, hlen, op_id, op_len, opcode, org_block, org_len, org, db, start, length, empty,
     empty_len) = _REQ.unpack(header)  # fmt: skip
    if (
        sysid != SYSTEM_ID
        or hlen != HEADER_LEN
        or (op_id, op_len, org_block, org_len, empty, empty_len) != (1, 3, 3, 8, 0xFF, 2)
        or opcode not in (OpCode.FETCH_REQUEST, OpCode.WRITE_REQUEST)
    ):
        raise RemoteProtocolError(f"malformed FETCH/WRITE request header {header.hex(' ')}")
    return opcode, org, db, start, length


def parse_ack_header(header: bytes) -> tuple[int, int]:
    """``(opcode, error)`` of an acknowledgement header; the 5 free bytes are ignored."""
    if len(header) != HEADER_LEN:
        raise RemoteProtocolError(f"FETCH/WRITE acknowledgement of {len(header)} bytes")
    sysid, hlen, op_id, op_len, opcode, ack_block, ack_len, error, empty, empty_len, _free = (
        _ACK.unpack(header)
    )
    if (
        sysid != SYSTEM_ID
        or hlen != HEADER_LEN
        or (op_id, op_len, ack_block, ack_len, empty, empty_len) != (1, 3, 0x0F, 3, 0xFF, 7)
        or opcode not in (OpCode.FETCH_RESPONSE, OpCode.WRITE_RESPONSE)
    ):
        raise RemoteProtocolError(f"malformed FETCH/WRITE acknowledgement {header.hex(' ')}")
    return opcode, error


# -- connections ---------------------------------------------------------------------------


class _Framed(ErrorState):
    """What both roles share: raw byte buffer or MK message framing, and the ERROR state."""

    def __init__(self, framing: Framing, mk: MkConnection | None) -> None:
        if framing not in ("raw", "mk"):
            raise ValueError(f"framing must be 'raw' or 'mk', not {framing!r}")
        self.framing: Framing = framing
        self.mk: MkConnection | None = (mk or MkConnection()) if framing == "mk" else None
        self._buf = ReceiveBuffer()

    def receive_data(self, data: bytes) -> None:
        if self.error is not None:
            self._check_usable()
        if self.mk is not None:
            self.mk.receive_data(data)
        else:
            self._buf.feed(data)

    @property
    def buffered(self) -> int:
        """Bytes received and not yet turned into events (part of a frame)."""
        return self.mk.buffered if self.mk is not None else len(self._buf)

    def _frame(self, payload: bytes) -> bytes:
        return self.mk.send_message(payload) if self.mk is not None else payload

    def _next_message(self) -> bytes | NeedData:
        """MK only: the next complete message, skipping life acks."""
        assert self.mk is not None
        while True:
            event = self.mk.next_event()
            if isinstance(event, LifeAck):
                continue
            if isinstance(event, Message):
                return event.data
            return event

    def life_ack(self) -> bytes:
        """A keep-alive telegram (MK framing only)."""
        if self.mk is None:
            raise LocalProtocolError("life acks exist only with the MK header")
        return self.mk.life_ack()


class ClientConnection(_Framed):
    """The PC side: ``send(FetchRequest|WriteRequest)``, then events until a response arrives."""

    def __init__(self, framing: Framing = "raw", *, mk: MkConnection | None = None) -> None:
        super().__init__(framing, mk)
        self._pending: Request | None = None
        self._ack: tuple[int, int] | None = None  # raw: header parsed, waiting for data

    @property
    def pending(self) -> Request | None:
        return self._pending

    def send(self, request: Request) -> bytes:
        if self.error is not None:
            self._check_usable()
        if self._pending is not None:  # [R] C.6.5: at most one job outstanding, no pipelining
            raise LocalProtocolError("a FETCH/WRITE job is already outstanding (no pipelining)")
        if not isinstance(request, FetchRequest | WriteRequest):
            raise LocalProtocolError(f"cannot send {type(request).__name__}")
        payload = encode_request(request)
        if isinstance(request, FetchRequest):
            data_bytes(request.org, request.length)  # unknown ORG: raw framing could not parse
        self._pending = request
        return self._frame(payload)

    def next_event(self) -> Response | NeedData:
        """The answer to the outstanding job, or ``NEED_DATA``; bytes that cannot be one raise
        :class:`RemoteProtocolError` and leave the connection in the ERROR state."""
        if self.error is not None:
            self._check_usable()
        try:
            return self._next_response()
        except RemoteProtocolError as exc:
            raise self._broken(exc) from None

    def _next_response(self) -> Response | NeedData:
        if self.mk is not None:
            message = self._next_message()
            if message is NEED_DATA:
                return NEED_DATA
            if self._pending is None:
                raise RemoteProtocolError("unsolicited FETCH/WRITE message with no job outstanding")
            return self._complete(message[:HEADER_LEN], message[HEADER_LEN:], framed=True)
        buf = self._buf
        if self._pending is None:
            if buf:
                raise RemoteProtocolError(
                    f"unsolicited bytes with no job outstanding: {buf.peek(16).hex(' ')}"
                )
            return NEED_DATA
        if len(buf) < HEADER_LEN:
            return NEED_DATA
        opcode, error = parse_ack_header(buf.peek(HEADER_LEN))
        self._check_opcode(opcode)
        need = self._expected_data(error)
        if len(buf) < HEADER_LEN + need:
            return NEED_DATA
        header = buf.take(HEADER_LEN)
        return self._complete(header, buf.take(need), framed=False)

    def _check_opcode(self, opcode: int) -> None:
        assert self._pending is not None
        want = (
            OpCode.FETCH_RESPONSE
            if isinstance(self._pending, FetchRequest)
            else OpCode.WRITE_RESPONSE
        )
        if opcode != want:
            raise RemoteProtocolError(
                f"acknowledgement opcode {opcode:#04x} does not answer the outstanding job "
                f"(expected {want:#04x})"
            )

    def _expected_data(self, error: int) -> int:
        pending = self._pending
        if isinstance(pending, FetchRequest) and error == 0:
            return data_bytes(pending.org, pending.length)
        return 0

    def _complete(self, header: bytes, data: bytes, *, framed: bool) -> Response:
        opcode, error = parse_ack_header(header)
        self._check_opcode(opcode)
        need = self._expected_data(error)
        if framed and len(data) != need:  # [R] C.7: cross-check the MK message length
            raise RemoteProtocolError(
                f"acknowledgement carries {len(data)} data bytes, the job needs {need}"
            )
        pending = self._pending
        self._pending = None
        if isinstance(pending, FetchRequest):
            return FetchResponse(error, data)
        return WriteResponse(error)


class ServerConnection(_Framed):
    """The CP/module side: events are requests; answer each with :meth:`send`."""

    def __init__(self, framing: Framing = "raw", *, mk: MkConnection | None = None) -> None:
        super().__init__(framing, mk)
        self._awaiting: int | None = None  # opcode of the request we still have to answer
        self._fetch_bytes = 0  # data bytes a successful FETCH acknowledgement must carry

    def next_event(self) -> FetchRequest | WriteRequest | BadRequest | NeedData:
        """The next request, or ``NEED_DATA``; a malformed header raises
        :class:`RemoteProtocolError` (C.6.5: close without an answer) and leaves the connection in
        the ERROR state."""
        if self.error is not None:
            self._check_usable()
        try:
            return self._next_request()
        except RemoteProtocolError as exc:
            raise self._broken(exc) from None

    def _next_request(self) -> FetchRequest | WriteRequest | BadRequest | NeedData:
        if self._awaiting is not None:
            return NEED_DATA  # one job at a time: answer the current one first
        if self.mk is not None:
            message = self._next_message()
            if message is NEED_DATA:
                return NEED_DATA
            event = self._decode(message[:HEADER_LEN], message[HEADER_LEN:], framed=True)
        else:
            buf = self._buf
            if len(buf) < HEADER_LEN:
                return NEED_DATA
            opcode, org, _db, _start, length = parse_request_header(buf.peek(HEADER_LEN))
            need = 0
            if opcode == OpCode.WRITE_REQUEST and org in _UNIT:
                need = _UNIT[org] * length
            if len(buf) < HEADER_LEN + need:
                return NEED_DATA
            header = buf.take(HEADER_LEN)
            event = self._decode(header, buf.take(need), framed=False)
        self._awaiting = (
            OpCode.FETCH_RESPONSE
            if isinstance(event, FetchRequest)
            or (isinstance(event, BadRequest) and event.opcode == OpCode.FETCH_REQUEST)
            else OpCode.WRITE_RESPONSE
        )
        self._fetch_bytes = (
            _UNIT[event.org] * event.length if isinstance(event, FetchRequest) else 0
        )
        return event

    @staticmethod
    def _decode(
        header: bytes, data: bytes, *, framed: bool
    ) -> FetchRequest | WriteRequest | BadRequest:
        if len(header) < HEADER_LEN:
            raise RemoteProtocolError(f"FETCH/WRITE message of {len(header)} bytes")
        opcode, org, db, start, length = parse_request_header(header)

        def bad(reason: str, close: bool = False) -> BadRequest:
            return BadRequest(opcode, org, db, start, length, 0x01, reason, close)

        is_write = opcode == OpCode.WRITE_REQUEST
        if org not in _UNIT:
            # Raw framing: the amount of WRITE data is unknown, so the stream cannot continue.
            return bad(f"unknown ORG ID {org:#04x}", close=is_write and not framed)
        if length == 0:
            return bad("length 0")
        want = _UNIT[org] * length if is_write else 0
        if framed and len(data) != want:
            # [R] C.6.5: a wrong data amount is error 01.
            return bad(f"message carries {len(data)} data bytes, the header announces {want}")
        if is_write:
            return WriteRequest(org, db, start, length, data)
        return FetchRequest(org, db, start, length)

    def send(self, response: Response) -> bytes:
        """Encode the acknowledgement of the request just returned by :meth:`next_event`."""
        if self.error is not None:
            self._check_usable()
        opcode = (
            OpCode.FETCH_RESPONSE if isinstance(response, FetchResponse) else OpCode.WRITE_RESPONSE
        )
        if self._awaiting is None:
            raise LocalProtocolError("no request to acknowledge")
        if opcode != self._awaiting:
            raise LocalProtocolError(f"the outstanding request needs opcode {self._awaiting:#04x}")
        data = response.data if isinstance(response, FetchResponse) else b""
        if (
            opcode == OpCode.FETCH_RESPONSE
            and response.error == 0
            and len(data) != self._fetch_bytes
        ):
            raise LocalProtocolError(
                f"FETCH acknowledgement needs {self._fetch_bytes} data bytes, got {len(data)}"
            )
        payload = encode_ack(opcode, response.error, data)
        self._awaiting = None
        return self._frame(payload)
