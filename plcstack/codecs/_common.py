"""Pieces every Sans-IO codec shares: the event base, the ERROR state, NEED_DATA, a buffer.

Every protocol has the same shape (h11/wsproto style): a ``ClientConnection`` and a
``ServerConnection`` per codec module, ``send(event) -> bytes``, ``receive_data(data)``,
``next_event() -> Event | NEED_DATA``. Events derive from :class:`Event`. A connection whose peer
sent bytes it refused (:class:`RemoteProtocolError`) is in the ERROR state (:class:`ErrorState`)
and refuses further use: it can no longer know where the next message starts.
"""

from __future__ import annotations

import enum
from typing import Final

from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = ["NEED_DATA", "ErrorState", "Event", "NeedData", "ReceiveBuffer"]


class Event:
    """Base of every codec event (requests, responses, acks, refusals) of every protocol.

    Events are frozen dataclasses with slots; this base adds no fields, so ``isinstance(x,
    Event)`` tells a protocol event from anything else (e.g. ``NEED_DATA``).
    """

    __slots__ = ()


class ErrorState:
    """The ERROR state of h11/wsproto for one connection object.

    A connection records the :class:`RemoteProtocolError` it raised (:meth:`_broken`); from then
    on :meth:`_check_usable` raises :class:`LocalProtocolError` naming that first error, so a
    caller cannot go on decoding a stream whose framing is lost. Make a new connection object
    (the clients do on reconnect).
    """

    #: the RemoteProtocolError that put this connection in the ERROR state, or None
    error: RemoteProtocolError | None = None

    @property
    def errored(self) -> bool:
        """Whether the connection is in the ERROR state."""
        return self.error is not None

    def _check_usable(self) -> None:
        if self.error is not None:
            raise LocalProtocolError(
                f"{type(self).__name__} is in the ERROR state after: {self.error.message}; "
                "use a new connection"
            )

    def _broken(self, exc: RemoteProtocolError) -> RemoteProtocolError:
        """Enter the ERROR state because of ``exc``; returns it for ``raise``."""
        if self.error is None:
            self.error = exc
        return exc


class NeedData(enum.Enum):
    """Returned by ``next_event()`` when more bytes must arrive before an event can be produced.

    An enum member rather than ``object()`` so that type checkers can narrow ``Event | NeedData``.
    """

    NEED_DATA = "NEED_DATA"

    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA: Final = NeedData.NEED_DATA


class ReceiveBuffer:
    """A byte buffer that consumes from the front without copying the tail each time.

    Stream decoders take a frame off the front once they know its length; ``bytearray`` deletion
    from the front is O(n), so we keep a read offset and compact only when it pays.
    """

    __slots__ = ("_buf", "_pos")

    def __init__(self) -> None:
        self._buf = bytearray()
        self._pos = 0

    def __len__(self) -> int:
        return len(self._buf) - self._pos

    def __bool__(self) -> bool:
        return len(self._buf) > self._pos

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        if self._pos and self._pos == len(self._buf):
            self._buf.clear()
            self._pos = 0
        self._buf += data

    def peek(self, n: int | None = None) -> bytes:
        """Up to ``n`` bytes from the front (all if ``None``) without consuming them."""
        end = len(self._buf) if n is None else min(len(self._buf), self._pos + n)
        return bytes(self._buf[self._pos : end])

    def __getitem__(self, index: int) -> int:
        if index < 0 or self._pos + index >= len(self._buf):
            raise IndexError(index)
        return self._buf[self._pos + index]

    def take(self, n: int) -> bytes:
        """Remove and return exactly ``n`` bytes; the caller has checked ``len(self) >= n``."""
        if n > len(self):
            raise ValueError(f"take({n}) with only {len(self)} bytes buffered")
        start = self._pos
        self._pos += n
        out = bytes(self._buf[start : self._pos])
        if self._pos > 4096 and self._pos * 2 > len(self._buf):
            del self._buf[: self._pos]
            self._pos = 0
        return out

    def take_prefixed(self, prefix: bytes, n: int) -> bytes | None:
        """Take exactly ``n`` bytes if that many are buffered and they start with ``prefix``;
        else ``None``, and nothing is taken (a decoder's fast path for a known answer)."""
        buf, pos = self._buf, self._pos
        if len(buf) - pos < n or not buf.startswith(prefix, pos):
            return None
        self._pos = end = pos + n
        out = bytes(buf[pos:end])
        if end > 4096 and end * 2 > len(buf):
            del buf[:end]
            self._pos = 0
        return out

    def take_all(self) -> bytes:
        return self.take(len(self))

    def clear(self) -> None:
        self._buf.clear()
        self._pos = 0
