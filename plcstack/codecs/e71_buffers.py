"""Fixed buffer communication of the E71 (spec §8): Sans-IO, both roles, binary and ASCII.

With procedure (§8.1) both sides are equal: either may send a data telegram
``60 00 · length (words) · words`` and the receiver answers ``E0 · end code``. One
:class:`FixedBufferConnection` per connection, for the partner (``role="partner"``) or the E71
(``role="e71"``). Events: :class:`FixedBufferData` (a telegram arrived: acknowledge it with
:meth:`~FixedBufferConnection.send_ack`) and :class:`FixedBufferAck` (the answer to our telegram).

Rules enforced: one telegram of ours in flight (a second before its answer is our misuse,
:class:`LocalProtocolError`); an answer without a telegram of ours is the peer's error
(:class:`RemoteProtocolError`); the peer's next telegram is only taken once we answered its
previous one (``next_event`` returns ``NEED_DATA`` until then). On the E71 side a
malformed telegram is not raised but reported as :class:`FixedBufferError` with the end code the
E71 sends (50H undefined subheader, 52H length outside 1-1017 / 1-508 words, 54H non-hex ASCII);
such a telegram is not stored and the buffered input is dropped (§8.1, seed Tab. 7-2).

Without procedure (§8.2) there is no framing at all: :class:`RawBufferConnection` only enforces
the 2046-byte limit per transfer.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Final, Literal

from plcstack.codecs._common import NEED_DATA, Event, NeedData, ReceiveBuffer
from plcstack.codecs.e71_commands import FIXED_BUFFER_MAX_WORDS, FixedBufferData
from plcstack.codecs.e71_wire import Code, Malformed, Reader, Writer
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "FIXED_BUFFER_END_CODES",
    "RAW_MAX_BYTES",
    "FixedBufferAck",
    "FixedBufferConnection",
    "FixedBufferData",
    "FixedBufferError",
    "RawBufferConnection",
]

#: end codes of fixed-buffer answers (seed Tab. 7-2)
FIXED_BUFFER_END_CODES: Final = {
    0x00: "normal completion",
    0x50: "data or response undefined (subheader)",
    0x52: "data length wrong",
    0x54: "ASCII conversion error",
}
#: without procedure: at most 2046 bytes per transfer, always binary (§8.2)
RAW_MAX_BYTES: Final = 2046


@dataclass(frozen=True, slots=True)
class FixedBufferAck(Event):
    """``E0`` + end code: the peer's answer to our telegram (00H = taken)."""

    end_code: int = 0

    @property
    def meaning(self) -> str:
        return FIXED_BUFFER_END_CODES.get(self.end_code, "undocumented end code")


@dataclass(frozen=True, slots=True)
class FixedBufferError(Event):
    """E71 side: a telegram the E71 refuses; answer it with :meth:`FixedBufferConnection.refuse`
    (``subheader | 80H`` + end code: ``E0 52``, or e.g. ``E5 50`` for a telegram starting 65H)."""

    end_code: int
    reason: str = ""
    subheader: int = 0x60


Role = Literal["partner", "e71"]


class FixedBufferConnection:
    """One fixed-buffer connection with procedure (TCP stream or UDP datagrams)."""

    def __init__(
        self,
        code: Code | str = Code.BINARY,
        *,
        role: Role = "partner",
        transport: Literal["tcp", "udp"] = "tcp",
    ) -> None:
        self.code = code if isinstance(code, Code) else Code(code)
        self.role = role
        self.transport = transport
        self._u = 2 if self.code is Code.ASCII else 1
        self._buf = ReceiveBuffer()
        self._datagrams: deque[bytes] = deque()
        #: our telegram waits for the peer's E0 answer
        self.awaiting_ack = False
        #: the peer's telegram waits for our E0 answer
        self.owe_ack = False

    # -- sending --------------------------------------------------------------------------------
    def send(self, event: FixedBufferData | FixedBufferAck | FixedBufferError) -> bytes:
        """One entry point for all three: a telegram (:meth:`send_data`), the answer to the
        peer's telegram (:meth:`send_ack`) or, E71 side, a refusal (:meth:`refuse`)."""
        if isinstance(event, FixedBufferData):
            return self.send_data(event.values)
        if isinstance(event, FixedBufferAck):
            return self.send_ack(event.end_code)
        if isinstance(event, FixedBufferError):
            return self.refuse(event)
        raise LocalProtocolError(f"cannot send {type(event).__name__} as a fixed-buffer message")

    def send_data(self, values: tuple[int, ...] | list[int]) -> bytes:
        """Encode a data telegram (1-1017 words binary, 1-508 ASCII)."""
        if self.awaiting_ack:
            raise LocalProtocolError("previous fixed-buffer telegram not answered yet")
        data = FixedBufferData(tuple(values)).encode(self.code)
        self.awaiting_ack = True
        return data

    def send_ack(self, end_code: int = 0) -> bytes:
        """Encode the answer ``E0`` + end code to the peer's telegram."""
        if not isinstance(end_code, int) or not 0 <= end_code <= 0xFF:
            raise LocalProtocolError(f"end code {end_code!r} outside 00H-FFH")
        if not self.owe_ack and end_code == 0:
            raise LocalProtocolError("no telegram of the peer to acknowledge")
        self.owe_ack = False
        w = Writer(self.code is Code.ASCII)
        w.num(0xE0, 1)
        w.num(end_code, 1)
        return w.getvalue()

    # -- receiving ------------------------------------------------------------------------------
    @property
    def max_held(self) -> int:
        """Bytes this connection holds received and undecoded at most: while we owe the peer
        our answer it may only have sent one telegram and its answer to ours (§8.1), so twice
        the largest telegram is generous; more is a peer that ignores the procedure."""
        return 2 * (4 + 2 * FIXED_BUFFER_MAX_WORDS[self.code]) * self._u

    @property
    def held(self) -> int:
        """Bytes received and not yet decoded (the counter the bound is tested on)."""
        return len(self._buf) + sum(len(d) for d in self._datagrams)

    def receive_data(self, data: bytes) -> None:
        if self.transport == "udp":
            if len(self._datagrams) >= 2:
                # one telegram and one answer may wait for our acknowledgement (§8.1)
                raise RemoteProtocolError(
                    "fixed buffer: the peer sent a third datagram while our answer to its "
                    "telegram was still owed (the procedure allows one at a time)"
                )
            self._datagrams.append(bytes(data))
            return
        if len(self._buf) + len(data) > self.max_held:
            raise RemoteProtocolError(
                f"fixed buffer: the peer sent more than {self.max_held} bytes while our answer "
                "to its telegram was still owed (the procedure allows one telegram at a time)"
            )
        self._buf.feed(data)

    def next_event(self) -> FixedBufferData | FixedBufferAck | FixedBufferError | NeedData:
        if self.owe_ack:
            # the peer's next telegram is only taken after we answered its previous one (§8.1)
            return NEED_DATA
        if self.transport == "udp":
            if not self._datagrams:
                return NEED_DATA
            data = self._datagrams.popleft()
            size = self._size(data)
            if isinstance(size, FixedBufferError):
                return size
            if size is None or size != len(data):
                return self._fail(0x52, f"datagram of {len(data)} bytes, telegram says {size}")
            return self._decode(data)
        buf = self._buf
        if not buf:
            return NEED_DATA
        size = self._size(buf.peek(16))
        if isinstance(size, FixedBufferError):
            buf.clear()
            return size
        if size is None or len(buf) < size:
            return NEED_DATA
        return self._decode(buf.take(size))

    def refuse(self, error: FixedBufferError) -> bytes:
        """E71 side: the answer to a refused telegram (§2: bit 7 set on its subheader)."""
        w = Writer(self.code is Code.ASCII)
        w.num((error.subheader | 0x80) & 0xFF, 1)
        w.num(error.end_code, 1)
        return w.getvalue()

    def _fail(self, end_code: int, reason: str, subheader: int = 0x60) -> FixedBufferError:
        if self.role == "partner":
            raise RemoteProtocolError(f"fixed buffer: {reason}")
        return FixedBufferError(end_code, reason, subheader)

    def _size(self, head: bytes) -> int | FixedBufferError | None:
        u = self._u
        if len(head) < u:
            return None
        sub = 0x7F  # [R] a non-hex ASCII subheader is answered FFH 54H, as in the core codec
        try:
            r = Reader(head, self.code is Code.ASCII)
            sub = r.num(1)
            if sub == 0xE0:
                return 2 * u
            if sub != 0x60:
                return self._fail(0x50, f"undefined subheader {sub:02X}H", sub)
            if len(head) < 4 * u:
                return None
            r.num(1)  # §13 A16: second subheader byte ignored
            n = r.num(2)
        except Malformed as exc:
            return self._fail(exc.end_code, exc.reason, sub)
        if not 1 <= n <= FIXED_BUFFER_MAX_WORDS[self.code]:
            return self._fail(
                0x52, f"data length {n} words outside 1-{FIXED_BUFFER_MAX_WORDS[self.code]}"
            )
        return (4 + 2 * n) * u

    def _decode(self, frame: bytes) -> FixedBufferData | FixedBufferAck | FixedBufferError:
        try:
            r = Reader(frame, self.code is Code.ASCII)
            sub = r.num(1)
            if sub == 0xE0:
                end = r.num(1)
                if not self.awaiting_ack:
                    return self._fail(0x50, "fixed buffer answer E0H without a telegram of ours")
                self.awaiting_ack = False
                return FixedBufferAck(end)
            r.num(1)
            values = r.words(r.num(2))
        except Malformed as exc:
            return self._fail(exc.end_code, exc.reason)
        self.owe_ack = True
        return FixedBufferData(values)


class RawBufferConnection:
    """Fixed buffer without procedure (§8.2): no header, no answer, always binary.

    On TCP each received chunk is delivered as it arrives ([R] — the E71 cannot know message
    boundaries either); on UDP one datagram is one message."""

    def __init__(self) -> None:
        self._chunks: deque[bytes] = deque()

    def send(self, data: bytes) -> bytes:
        if not isinstance(data, (bytes, bytearray)) or not 1 <= len(data) <= RAW_MAX_BYTES:
            raise LocalProtocolError(f"without procedure: 1-{RAW_MAX_BYTES} bytes per transfer")
        return bytes(data)

    def receive_data(self, data: bytes) -> None:
        if data:
            self._chunks.append(bytes(data))

    def next_event(self) -> bytes | NeedData:
        return self._chunks.popleft() if self._chunks else NEED_DATA
