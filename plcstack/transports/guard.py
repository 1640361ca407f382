"""What every listening face does against clients that are slow, silent, many or hostile.

The gateway's S5-LAN and FETCH/WRITE servers, the Modbus TCP server and the simulators listen
on plant networks, where a scanner, a half-open socket or a broken panel is a matter of time.
Three bounds keep such a client from holding what the others need:

* :class:`IdleWatch`: a connection that sends nothing for ``timeout`` seconds is ended (a dead
  partner would otherwise hold one of the few connections for ever);
* :class:`FrameDeadline`: a frame once begun must be complete within ``limit`` seconds of its
  *first* byte. A per-read timeout does not do it: a client that sends one header byte every
  half second restarts it with every byte and holds its connection for ever (slowloris);
* :class:`ClientLimit`: at most ``limit`` clients at once; the next one is turned away at once
  and counted, and the log says so once per burst, not once per connection of a flood;
* :func:`close_writer`: a stream closed after its answer, aborted if the peer does not read it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable

__all__ = [
    "CLOSE_LINGER",
    "FRAME_TIMEOUT",
    "ClientLimit",
    "FrameDeadline",
    "IdleWatch",
    "close_writer",
]

#: seconds a request frame may take from its first byte to its last. Frames of these protocols
#: are at most a few KiB (a FETCH/WRITE write: 128 KiB), sent in one go by every real client;
#: only a client that trickles them, to hold a connection, takes longer.
FRAME_TIMEOUT = 5.0

#: seconds a closing connection may take to send what is still queued for a peer that reads
#: nothing, before it is aborted
CLOSE_LINGER = 1.0


async def close_writer(writer: asyncio.StreamWriter) -> None:
    """Close a client's stream and take how it ended.

    asyncio keeps the end of a connection (a reset by the peer, say) in a future that only
    ``wait_closed()`` reads. Left unread, the garbage collector may report it as "Future
    exception was never retrieved" (whether it does depends on the order it frees things in):
    noise that reads like a fault of the server. A peer that reads nothing would hold the
    close for ever (the answer still queued), so after :data:`CLOSE_LINGER` seconds the
    connection is aborted. A cancel while closing (the server stops) aborts too and ends
    normally, as the handlers that call this end on a cancel.
    """
    writer.close()
    try:
        async with asyncio.timeout(CLOSE_LINGER):
            await writer.wait_closed()
    except (ConnectionError, OSError):
        pass  # the peer reset or left: the outcome is read, nothing more to do
    except (TimeoutError, asyncio.CancelledError):
        writer.transport.abort()
        with contextlib.suppress(ConnectionError, OSError, asyncio.CancelledError):
            await writer.wait_closed()


class IdleWatch:
    """Calls ``on_idle`` once ``timeout`` seconds passed without :meth:`touch`.

    One timer per connection, re-armed only when it fires (``touch`` just stores the time), so
    a busy connection costs one attribute write per chunk received.
    """

    __slots__ = ("_handle", "_last", "_loop", "on_idle", "timeout")

    def __init__(self, timeout: float | None, on_idle: Callable[[], None]) -> None:
        self.timeout = timeout
        self.on_idle = on_idle
        self._loop = asyncio.get_running_loop()
        self._last = self._loop.time()
        self._handle: asyncio.TimerHandle | None = None
        if timeout is not None:
            self._handle = self._loop.call_later(timeout, self._fire)

    def touch(self) -> None:
        self._last = self._loop.time()

    def cancel(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None

    def _fire(self) -> None:
        assert self.timeout is not None
        due = self._last + self.timeout
        if self._loop.time() >= due:
            self._handle = None
            self.on_idle()
        else:
            self._handle = self._loop.call_at(due, self._fire)


class FrameDeadline:
    """When the frame being received must be complete: ``limit`` seconds after its first byte.

    Call :meth:`note` after each chunk with whether part of a frame is still buffered. A server
    that reads in a loop waits until :attr:`due`; a protocol-callback server passes
    ``on_expire``, called once when a frame is still incomplete at its deadline.
    """

    __slots__ = ("_handle", "_loop", "limit", "on_expire", "started")

    def __init__(self, limit: float | None, on_expire: Callable[[], None] | None = None) -> None:
        self.limit = limit
        self.on_expire = on_expire
        self.started: float | None = None
        self._loop = asyncio.get_running_loop()
        self._handle: asyncio.TimerHandle | None = None

    @property
    def due(self) -> float | None:
        """Loop time at which the frame begun must be complete (None: no frame begun)."""
        if self.started is None or self.limit is None:
            return None
        return self.started + self.limit

    def note(self, buffered: bool) -> None:
        """Part of a frame is buffered (its clock starts now if it did not run), or none is."""
        if not buffered:
            self.started = None
            self.cancel()
        elif self.started is None:
            self.started = self._loop.time()
            if self.on_expire is not None and self.limit is not None:
                self._handle = self._loop.call_later(self.limit, self._fire)

    def cancel(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None

    def _fire(self) -> None:
        self._handle = None
        if self.on_expire is not None:
            self.on_expire()


class ClientLimit:
    """At most ``limit`` clients of one server at once (``None``: no limit).

    :meth:`admit` says whether a new client may stay; a refused one is counted in ``refused``
    and the first refusal of a burst is logged (WARNING) with ``what`` naming the server; the
    next is logged again only after the server was below its limit once more.
    """

    __slots__ = ("_said", "current", "limit", "log", "refused", "what")

    def __init__(self, limit: int | None, what: str, log: logging.Logger) -> None:
        if limit is not None and limit < 1:
            raise ValueError(f"{what}: a client limit must be at least 1, not {limit}")
        self.limit = limit
        self.what = what
        self.log = log
        self.current = 0
        self.refused = 0
        self._said = False

    def admit(self, peer: str | None, *, current: int | None = None) -> bool:
        """Count the client in, or refuse it (False): the caller closes its connection.
        ``current``: the clients connected now, for a server that counts them itself (then
        :meth:`release` is not called)."""
        if current is not None:
            self.current = current
        if self.limit is not None and self.current >= self.limit:
            self.refused += 1
            if not self._said:
                self._said = True
                self.log.warning(
                    "%s: %d clients connected, the limit; refusing %s and more until one leaves",
                    self.what,
                    self.current,
                    peer or "a client",
                )
            return False
        if self._said:
            self._said = False
            self.log.info(
                "%s: below its limit of %d clients again (%d refused so far)",
                self.what,
                self.limit,
                self.refused,
            )
        self.current += 1
        return True

    def release(self) -> None:
        """A client admitted has gone."""
        self.current -= 1
