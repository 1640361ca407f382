"""Modbus TCP frames, server side, Sans-IO: bytes in, :class:`Request` objects out, answers out.

Why not pymodbus's server. pymodbus 3.x (read at 3.16) hands each decoded request to a datastore
through ``ModbusServerContext.async_getValues``/``async_setValues``; that context class is
deprecated for its simulator core in 4.0, the request handler keeps one ``last_pdu`` per
connection and runs it in a coroutine scheduled with ``call_soon`` (a second request arriving
before the first is answered replaces it), FC 5 and 6 answer by reading the datastore back
after the write (so an answer would show the last poll, not what was written), and its framer
treats a frame with a non-zero protocol identifier as "wait for more data", so such a peer
hangs instead of being dropped. The answers this server must give per request (0x0B for a tag
whose PLC does not answer, a write answered only after the PLC confirmed it, in request order)
need the request handling in our hands; what is left, the MBAP header and the eight function
codes' PDUs, is this module. The server then has no third-party dependency at all, and the tests
check it against an independent implementation (libmodbus).

Frame (Modbus Messaging on TCP/IP Implementation Guide V1.0b, Modbus Application Protocol
V1.1b3): MBAP header ``transaction id (2) | protocol id (2) = 0 | length (2) | unit id (1)``, then
the PDU ``function code (1) | data``; ``length`` counts the unit id and the PDU. Broken framing
(protocol id not 0, length outside 2..254) raises :class:`RemoteProtocolError`: the connection is
closed, since nothing after it can be trusted. A well-framed PDU that is wrong (unknown function,
a count out of range, a byte count that does not match) becomes a request carrying the exception
code to answer with (:attr:`Request.error`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from plcstack.errors import RemoteProtocolError

__all__ = [
    "EXCEPTION_NAMES",
    "FUNCTIONS",
    "ModbusServerConnection",
    "Request",
    "encode_bits",
    "exception_frame",
    "response_frame",
]

#: exception codes answered (Modbus Application Protocol 7)
ILLEGAL_FUNCTION = 0x01
ILLEGAL_ADDRESS = 0x02
ILLEGAL_VALUE = 0x03
DEVICE_FAILURE = 0x04
DEVICE_BUSY = 0x06
GATEWAY_PATH_UNAVAILABLE = 0x0A
GATEWAY_NO_RESPONSE = 0x0B
EXCEPTION_NAMES = {
    ILLEGAL_FUNCTION: "illegal function",
    ILLEGAL_ADDRESS: "illegal data address",
    ILLEGAL_VALUE: "illegal data value",
    DEVICE_FAILURE: "server device failure",
    DEVICE_BUSY: "server device busy",
    GATEWAY_PATH_UNAVAILABLE: "gateway path unavailable",
    GATEWAY_NO_RESPONSE: "gateway target device failed to respond",
}

#: function code -> (table, is a write, largest quantity)
FUNCTIONS: dict[int, tuple[str, bool, int]] = {
    1: ("co", False, 2000),
    2: ("di", False, 2000),
    3: ("hr", False, 125),
    4: ("ir", False, 125),
    5: ("co", True, 1),
    6: ("hr", True, 1),
    15: ("co", True, 1968),
    16: ("hr", True, 123),
}
_HEADER = struct.Struct(">HHHB")
_ADDRESS_COUNT = struct.Struct(">HH")
#: longest frame: MBAP (7) + the largest PDU (253)
MAX_FRAME = 260


@dataclass(frozen=True, slots=True)
class Request:
    """One request. ``values`` are the words (FC 6, 16) or bits as 0/1 (FC 5, 15) to write.
    ``error`` is non-zero when the PDU itself is refused with that exception code."""

    transaction: int
    unit: int
    function: int
    address: int = 0
    count: int = 0
    values: tuple[int, ...] = ()
    error: int = 0

    @property
    def known(self) -> bool:
        """One of the eight function codes served."""
        return self.function in FUNCTIONS

    @property
    def table(self) -> str:
        return FUNCTIONS[self.function][0]

    @property
    def is_write(self) -> bool:
        return FUNCTIONS[self.function][1]


class ModbusServerConnection:
    """The server side of one Modbus TCP connection: feed bytes, take requests."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def receive_data(self, data: bytes) -> None:
        self._buffer += data

    @property
    def buffered(self) -> int:
        """Bytes received and not yet taken as requests (a partial frame, or requests the
        server has not come to yet)."""
        return len(self._buffer)

    def next_request(self) -> Request | None:
        """The next complete request, or None until more data arrived."""
        buf = self._buffer
        if len(buf) < 7:
            return None
        transaction, protocol, length, unit = _HEADER.unpack_from(buf)
        if protocol != 0:
            raise RemoteProtocolError(f"Modbus TCP frame with protocol id {protocol}, not 0")
        if not 2 <= length <= 254:
            raise RemoteProtocolError(f"Modbus TCP frame with length {length}, not 2..254")
        if len(buf) < 6 + length:
            return None
        pdu = bytes(buf[7 : 6 + length])
        del buf[: 6 + length]
        return _decode_pdu(transaction, unit, pdu)


def _decode_pdu(transaction: int, unit: int, pdu: bytes) -> Request:
    function = pdu[0]
    spec = FUNCTIONS.get(function)
    if spec is None:
        return Request(transaction, unit, function, error=ILLEGAL_FUNCTION)
    _, write, limit = spec
    data = pdu[1:]

    def refused(code: int, address: int = 0, count: int = 0) -> Request:
        return Request(transaction, unit, function, address, count, error=code)

    if len(data) < 4:
        return refused(ILLEGAL_VALUE)
    address, second = _ADDRESS_COUNT.unpack_from(data)
    if function in (5, 6):
        if len(data) != 4:
            return refused(ILLEGAL_VALUE, address, 1)
        if function == 5:
            if second not in (0x0000, 0xFF00):
                return refused(ILLEGAL_VALUE, address, 1)
            return Request(transaction, unit, function, address, 1, (1 if second else 0,))
        return Request(transaction, unit, function, address, 1, (second,))
    count = second
    if not 1 <= count <= limit:
        return refused(ILLEGAL_VALUE, address, count)
    if address + count > 0x10000:
        return refused(ILLEGAL_ADDRESS, address, count)
    if not write:
        if len(data) != 4:
            return refused(ILLEGAL_VALUE, address, count)
        return Request(transaction, unit, function, address, count)
    byte_count = data[4] if len(data) > 4 else -1
    expected = (count + 7) // 8 if function == 15 else 2 * count
    if byte_count != expected or len(data) != 5 + expected:
        return refused(ILLEGAL_VALUE, address, count)
    payload = data[5:]
    values: tuple[int, ...]
    if function == 15:
        values = tuple((payload[i // 8] >> (i % 8)) & 1 for i in range(count))
    else:
        values = struct.unpack(f">{count}H", payload)
    return Request(transaction, unit, function, address, count, values)


def encode_bits(bits: list[int]) -> bytes:
    """Bits packed eight to a byte, the first in the lowest bit (FC 1, 2, 15)."""
    out = bytearray((len(bits) + 7) // 8)
    for i, bit in enumerate(bits):
        if bit:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def _frame(request: Request, pdu: bytes) -> bytes:
    return _HEADER.pack(request.transaction, 0, len(pdu) + 1, request.unit) + pdu


def response_frame(request: Request, values: list[int] | None = None) -> bytes:
    """The normal answer: the values read (words, or bits as 0/1), or a write's echo."""
    function = request.function
    if function in (1, 2):
        data = encode_bits(values or [])
        return _frame(request, bytes((function, len(data))) + data)
    if function in (3, 4):
        words = values or []
        return _frame(
            request, bytes((function, 2 * len(words))) + struct.pack(f">{len(words)}H", *words)
        )
    if function == 5:
        value = 0xFF00 if request.values[0] else 0
        return _frame(request, struct.pack(">BHH", function, request.address, value))
    if function == 6:
        return _frame(request, struct.pack(">BHH", function, request.address, request.values[0]))
    return _frame(request, struct.pack(">BHH", function, request.address, request.count))


def exception_frame(request: Request, code: int) -> bytes:
    """An exception answer: the function code with its high bit set, then the code."""
    return _frame(request, bytes(((request.function | 0x80) & 0xFF, code)))
