"""The Tani "SPS-Header" (MK header) framing, spec part C.1-C.5. Sans-IO, both directions.

Each telegram is ``'M' 'K' | DataLen (LE16) | Flags (LE16, bit 0 = more follows) | SeqNo (LE16)``
followed by ``DataLen`` bytes of user data. A telegram with DataLen 0 is a life data ack
(keep-alive). One application message may span several telegrams; the continuation bit glues them
together. The framing is symmetric, so one class serves the client and the module side.

Clocks: the codec never reads one. :class:`LifeAckTimer` is a small pure helper that the asyncio
layers (client keep-alive task, simulator connection loop) feed with ``now`` values.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Final

from plcstack.codecs._common import NEED_DATA, ErrorState, Event, NeedData, ReceiveBuffer
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "HEADER_LEN",
    "MAGIC",
    "MAX_MESSAGE",
    "MAX_RECEIVE_DATA",
    "MAX_SEND_DATA",
    "LifeAck",
    "LifeAckTimer",
    "Message",
    "MkConnection",
    "encode_telegram",
]

MAGIC: Final = b"MK"
HEADER_LEN: Final = 8
#: user data bytes per sent telegram (the Tani "Kachel" size) [S-MK]
MAX_SEND_DATA: Final = 512
#: largest telegram data a Tani module documents receiving [S-MK]; enforced in strict mode only
MAX_RECEIVE_DATA: Final = 1460
#: reassembly guard: a message growing beyond this is an error and closes the connection [R]
MAX_MESSAGE: Final = 70000

_HEADER = struct.Struct("<2sHHH")
_FLAG_MORE: Final = 0x0001


@dataclass(frozen=True, slots=True)
class Message(Event):
    """One reassembled application message (the data of 1..n telegrams)."""

    data: bytes
    #: SeqNo of the first and number of telegrams it arrived in (diagnostics, tests)
    first_seq: int = 0
    telegrams: int = 1


@dataclass(frozen=True, slots=True)
class LifeAck(Event):
    """A received life data ack (DataLen 0). Never answered (C.3)."""

    seq: int


def encode_telegram(data: bytes, seq: int, more: bool = False) -> bytes:
    """One telegram: 8-byte header plus ``data`` (``b""`` gives a life ack)."""
    if len(data) > 0xFFFF:
        raise LocalProtocolError(f"MK telegram data of {len(data)} bytes exceeds 65535")
    return _HEADER.pack(MAGIC, len(data), _FLAG_MORE if more else 0, seq & 0xFFFF) + data


class MkConnection(ErrorState):
    """MK framing for one TCP connection (one direction's counter each way).

    Sending: :meth:`send_message` splits a message into telegrams of at most ``max_send_data``
    bytes, each carrying the next SeqNo; :meth:`life_ack` builds a keep-alive that carries the
    current counter without incrementing it.

    Receiving: :meth:`receive_data` then :meth:`next_event` until ``NEED_DATA``; events are
    :class:`Message` (complete, reassembled) and :class:`LifeAck`.

    Sequence numbers (C.2) are checked by default (``check_seq=True``): the base is learned from
    the first data telegram (so both the 0-first and the 1-first convention pass), every further
    data telegram must carry +1, and a mismatch raises :class:`RemoteProtocolError`. The counter
    is the only thing that tells a delayed copy of an earlier answer from the answer to the
    request just sent (measured without the check: up to 440 wrong values per 3000 reads).
    ``check_seq=False`` is the documented way off for CPs that do not count (mismatches are
    then only counted in ``sequence_mismatches``). ``strict=True`` also rejects reserved flag
    bits and telegrams with more than 1460 data bytes.
    """

    def __init__(
        self,
        *,
        strict: bool = False,
        check_seq: bool = True,
        max_send_data: int = MAX_SEND_DATA,
        max_message: int = MAX_MESSAGE,
    ) -> None:
        if not 1 <= max_send_data <= 0xFFFF:
            raise ValueError("max_send_data must be in 1..65535")
        self.strict = strict
        self.check_seq = check_seq or strict
        self.max_send_data = max_send_data
        self.max_message = max_message
        # [R] D.C1: the header carries the counter *before* the increment; 0 on a new connection.
        self.tx_seq = 0
        self.expected_rx_seq: int | None = None
        self.sequence_mismatches = 0
        self.life_acks_received = 0
        self._buf = ReceiveBuffer()
        self._parts: list[bytes] = []
        self._parts_len = 0
        self._first_seq = 0

    # -- sending ------------------------------------------------------------------------------
    def send(self, event: Message | LifeAck) -> bytes:
        """``send(Message(data))``: :meth:`send_message`; ``send(LifeAck(...))``: :meth:`life_ack`
        (a life ack always carries the current counter, whatever ``seq`` the event holds)."""
        if isinstance(event, Message):
            return self.send_message(event.data)
        if isinstance(event, LifeAck):
            return self.life_ack()
        raise LocalProtocolError(f"cannot send {type(event).__name__} over MK")

    def send_message(self, data: bytes) -> bytes:
        """The telegrams carrying ``data``, concatenated, ready for one ``transport.write``."""
        if self.error is not None:
            self._check_usable()
        if not data:
            raise LocalProtocolError("an MK message cannot be empty (DataLen 0 is a life ack)")
        seq = self.tx_seq
        if len(data) <= self.max_send_data:  # one telegram (every request of a poller)
            self.tx_seq = (seq + 1) & 0xFFFF
            return _HEADER.pack(MAGIC, len(data), 0, seq) + data
        out = bytearray()
        step = self.max_send_data  # [R] C.4: 512-byte telegrams, bit 0 set on all but the last
        for pos in range(0, len(data), step):
            chunk = data[pos : pos + step]
            out += encode_telegram(chunk, self.tx_seq, more=pos + step < len(data))
            self.tx_seq = (self.tx_seq + 1) & 0xFFFF
        return bytes(out)

    def life_ack(self) -> bytes:
        """A life data ack carrying the current counter (not incremented, C.2)."""
        return encode_telegram(b"", self.tx_seq)

    # -- receiving ----------------------------------------------------------------------------
    def receive_data(self, data: bytes) -> None:
        if self.error is not None:
            self._check_usable()
        self._buf.feed(data)

    @property
    def buffered(self) -> int:
        """Bytes received and not yet turned into events."""
        return len(self._buf) + self._parts_len

    def next_event(self) -> Message | LifeAck | NeedData:
        """The next message or life ack, or ``NEED_DATA``; a framing error raises
        :class:`RemoteProtocolError` and leaves the connection in the ERROR state."""
        if self.error is not None:
            self._check_usable()
        try:
            return self._next_event()
        except RemoteProtocolError as exc:
            raise self._broken(exc) from None

    def _next_event(self) -> Message | LifeAck | NeedData:
        buf = self._buf
        while True:
            if len(buf) < HEADER_LEN:
                if (len(buf) >= 2 and buf.peek(2) != MAGIC) or (
                    len(buf) == 1 and buf[0] != MAGIC[0]
                ):
                    raise RemoteProtocolError(f"MK framing error: telegram starts {buf.peek(2)!r}")
                return NEED_DATA
            magic, length, flags, seq = _HEADER.unpack(buf.peek(HEADER_LEN))
            if magic != MAGIC:  # [R] C.1: a framing error closes the connection
                raise RemoteProtocolError(
                    f"MK framing error: telegram starts {magic.hex(' ')}, expected 4d 4b"
                )
            # [R] C.1/C.4: reserved flags and DataLen > 1460 are tolerated unless strict.
            if self.strict and flags & ~_FLAG_MORE:
                raise RemoteProtocolError(f"MK telegram with reserved flag bits set ({flags:#06x})")
            if self.strict and length > MAX_RECEIVE_DATA:
                raise RemoteProtocolError(
                    f"MK telegram with {length} data bytes exceeds {MAX_RECEIVE_DATA}"
                )
            if len(buf) < HEADER_LEN + length:
                return NEED_DATA
            buf.take(HEADER_LEN)
            if length == 0:
                # Life acks are never part of reassembly and their SeqNo is never checked.
                self.life_acks_received += 1
                return LifeAck(seq)
            data = buf.take(length)
            self._check_seq(seq)
            if not self._parts:
                self._first_seq = seq
            self._parts.append(data)
            self._parts_len += length
            if self._parts_len > self.max_message:  # [R] C.4 reassembly guard
                raise RemoteProtocolError(
                    f"MK message exceeds {self.max_message} bytes (continuation never ended)"
                )
            if flags & _FLAG_MORE:
                continue
            message = Message(b"".join(self._parts), self._first_seq, len(self._parts))
            self._parts.clear()
            self._parts_len = 0
            return message

    def _check_seq(self, seq: int) -> None:
        expected = self.expected_rx_seq
        self.expected_rx_seq = (seq + 1) & 0xFFFF
        if expected is None or seq == expected:
            return
        self.sequence_mismatches += 1
        if self.check_seq:
            raise RemoteProtocolError(
                f"MK sequence number {seq} where {expected} was expected (a delayed copy of an "
                "earlier telegram, or a CP that does not count: then use mk_seq=0)"
            )


class LifeAckTimer:
    """When to send a life ack and when the peer counts as dead (C.3, D.C4). Pure; feed it ``now``.

    ``interval``: send a life ack after that long without sending anything (``None``: never).
    ``timeout``: the peer is dead when nothing at all arrived for that long (``None``: never).
    """

    def __init__(self, interval: float | None, timeout: float | None, now: float) -> None:
        if (interval is not None and interval <= 0) or (timeout is not None and timeout <= 0):
            raise ValueError("life ack interval and timeout must be positive")
        self.interval = interval
        self.timeout = timeout
        self.last_tx = now
        self.last_rx = now

    def sent(self, now: float) -> None:
        self.last_tx = now

    def received(self, now: float) -> None:
        self.last_rx = now

    def ack_due(self, now: float) -> bool:
        return self.interval is not None and now - self.last_tx >= self.interval

    def dead(self, now: float) -> bool:
        return self.timeout is not None and now - self.last_rx >= self.timeout

    def next_wakeup(self) -> float | None:
        """The earliest time at which :meth:`ack_due` or :meth:`dead` can become true."""
        times = []
        if self.interval is not None:
            times.append(self.last_tx + self.interval)
        if self.timeout is not None:
            times.append(self.last_rx + self.timeout)
        return min(times) if times else None
