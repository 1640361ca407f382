"""The transport contract every protocol client is written against.

A transport moves bytes and nothing else: it does not know where one message ends. Stream
transports (TCP, serial) hand out whatever chunk arrived; datagram transports (UDP) hand out one
datagram per ``read()``. Clients pass ``read()`` an absolute deadline (event-loop time) and call
``abort()`` when it passes, so a late reply dies with the connection.
"""

from __future__ import annotations

import asyncio
import collections
import select
import weakref
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from plcstack.errors import ConnectFailed, ConnectionLost, PlcTimeout
from plcstack.transports.deadlines import deadlines_of, future_factory
from plcstack.transports.tap import ConnectionTap, Tap, recorded_send

__all__ = [
    "HELD_UP",
    "MAX_QUEUED",
    "ProtocolTransport",
    "QueueProtocolMixin",
    "ReceiveCounters",
    "Receiver",
    "Transport",
    "open_with_timeout",
]

T = TypeVar("T")


class Receiver(Protocol):
    """Who takes a connection's chunks as they arrive (:meth:`Transport.send_delivering`),
    instead of a reader awaiting :meth:`Transport.read`: a client's callback-driven exchange."""

    def chunk_received(self, data: bytes) -> None:
        """A chunk (stream) or datagram arrived."""

    def receive_failed(self, exc: Exception) -> None:
        """The delivery ended without the receiver stopping it: ``TimeoutError`` when its
        deadline passed, :class:`ConnectionLost` when the connection ended. Called once; the
        receiver is detached before."""


class Transport(ABC):
    """An open-able, re-open-able byte pipe to one peer."""

    #: human-readable peer, e.g. ``127.0.0.1:5000`` or ``/dev/ttyS0``
    peer: str

    @property
    @abstractmethod
    def is_open(self) -> bool: ...

    @abstractmethod
    async def open(self, timeout: float | None) -> None:
        """Connect; raises ``ConnectFailed`` or ``PlcTimeout``. Re-openable after a close."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Queue bytes (one datagram for UDP). Raises :class:`ConnectionLost` when not open."""

    @abstractmethod
    async def read(self, deadline: float | None = None) -> bytes:
        """Next received chunk (stream) or datagram. Raises :class:`ConnectionLost` at EOF and
        ``TimeoutError`` when ``deadline`` (``loop.time()`` based; ``None`` = never) passes first.

        The deadline is a parameter rather than an ``asyncio.timeout`` around the call because it
        is on every request's hot path: one timer handle on the wait future costs a fraction of a
        timeout context (measured: the context was a third of the client's per-request overhead).
        """

    @abstractmethod
    def abort(self) -> None:
        """Close now, dropping anything buffered in either direction. Idempotent."""

    async def aclose(self) -> None:
        """Close cleanly (flush what was written). The default is an abort."""
        self.abort()

    @property
    def arrived(self) -> float | None:
        """Loop time at which the newest chunk handed out by :meth:`read` arrived (when the
        transport's data callback ran), ``None`` when unknown.

        A driver that times bytes (the AS511 character timeout) counts from here rather than
        from when its own coroutine resumed: other callbacks may have run in between."""
        return None

    def take_received(self) -> list[bytes]:
        """Chunks (datagrams) received and not yet read, without waiting; empties the queue.

        The request clients check between requests that nothing unsolicited arrived."""
        return []

    def quiet(self) -> bool:
        """Open, nothing received and unread, and nothing waiting in the OS: a request may be
        sent at once, without the stale-input check's loop passes (see ``input_waiting``).

        One call for the polling hot path; ``False`` (the default) sends every request down
        the general path, which is always correct.
        """
        return False

    def input_waiting(self) -> bool:
        """Whether bytes may wait in the OS that the event loop has not handed to us yet.

        ``True`` when the transport cannot tell (the default): the client then lets the loop
        run once before a request, so that such bytes reach ``take_received``. A transport
        that can ask the OS cheaply (TCP: one ``poll``) answers ``False`` when nothing waits,
        which spares every request that loop pass.
        """
        return True

    def send_delivering(self, data: bytes, receiver: Receiver, timeout: float) -> None:
        """:meth:`write` ``data``, then hand every chunk that arrives to ``receiver`` as it
        arrives, until :meth:`stop_delivery` or until ``timeout`` seconds have passed or the
        connection ends (then ``receiver.receive_failed``). Raises as ``write`` does, and
        then attaches nothing.

        How every request of a request/response client is sent (the exchange driver,
        ``clients/exchange.py``): a polled read then costs no future and no task step per
        answer, where ``read`` costs both; and one call where ``write`` and attaching the
        receiver were two. ``read`` serves the byte-by-byte AS511 dialogue. The timeout is relative,
        unlike ``read``'s deadline: the transport knows its loop, and asking for the running
        loop costs a system call (``getpid``).
        """
        raise NotImplementedError(f"{type(self).__name__} does not deliver to receivers")

    def stop_delivery(self) -> None:
        """Detach the receiver of :meth:`send_delivering` (nothing when none is attached)."""

    def record_to(self, tap: Tap | None) -> None:
        """Record this transport's connections in ``tap`` from the next ``open`` on (None:
        stop recording them); a ``capturing`` block records them as well."""
        raise NotImplementedError(f"{type(self).__name__} cannot record its connections")


#: seconds a deadline's timer may run late before the event loop counts as held up: it was
#: busy (a long callback, the process not scheduled) and did not watch the line, so it saw no
#: silence. Timers of a loaded but working loop run a few milliseconds late; a driver whose
#: timeout is short (the AS511 character timeout, 0.5 s) then waits once more (see the codec's
#: ``held_up``) instead of failing a transaction whose answer was coming.
HELD_UP = 0.05


#: bytes a connection holds received and unread before it stops reading (TCP, serial) or drops
#: datagrams (UDP). The largest legal answer of our protocols is a little over 2 KiB (S5-LAN,
#: FETCH/WRITE), so 64 KiB is a small multiple of it; a peer that streams to an idle client
#: (measured before: 2 GB in 10 s over TCP) is held here, the rest stays in the kernel's buffer
#: and TCP flow control stops the peer.
MAX_QUEUED = 64 * 1024


@dataclass
class ReceiveCounters:
    """What a transport's receive queue holds and has held: the receive-queue bound is
    asserted on these, not on the process's memory."""

    #: bytes received and not yet read now
    queued: int = 0
    #: the most ``queued`` ever was
    peak: int = 0
    #: times reading was paused because ``queued`` passed the limit (stream transports)
    pauses: int = 0
    #: datagrams (UDP) dropped because ``queued`` passed the limit, and their bytes
    dropped: int = 0
    dropped_bytes: int = 0


class QueueProtocolMixin:
    """asyncio protocol half shared by TCP, UDP and serial: a chunk queue and one waiting reader.

    Hand-rolled instead of ``asyncio.StreamReader`` because the hot path of a poll is "write, wait
    for one short reply": one future per wait and no extra buffering copies keep us close to the
    raw-asyncio floor the benchmarks compare against.

    The queue is bounded by ``max_queued`` bytes: above it a stream transport pauses reading
    (asyncio flow control; resumed once the reader took the queue) and a datagram transport
    drops what arrives, counting it. Nobody reads between requests, so only a peer sending
    unasked can fill it; the request clients then find those bytes and reconnect.
    """

    #: drop datagrams instead of pausing (UDP: a datagram socket cannot push back)
    _drop_when_full = False
    #: the recorder of this connection's bytes (:mod:`.tap`); set by the tapped subclasses only
    wire: ConnectionTap | None = None

    def _init_queue(self, peer: str, max_queued: int = MAX_QUEUED) -> None:
        self._peer = peer
        #: loop time at which the newest queued chunk arrived (``Transport.arrived``)
        self.arrived: float | None = None
        self._chunks: collections.deque[bytes] = collections.deque()
        self.max_queued = max_queued
        self.counters = ReceiveCounters()
        self._paused = False
        self._flow: asyncio.BaseTransport | None = None
        self._waiter: asyncio.Future[None] | None = None
        self._closed_exc: BaseException | None = None
        #: deadline of the wait in progress (``None``: none, or a wait without deadline)
        self._deadline: float | None = None
        #: whether the one deadline timer is armed, and the loop time it is armed for
        self._timer = False
        self._timer_at = 0.0
        #: the deadline whose expiry waits for input found in the kernel, and how many times
        #: it did (:meth:`_input_pending`)
        self._deferred_for: float | None = None
        self._deferrals = 0
        #: a ``poll`` on the connection's descriptor, made when a deadline first expires
        self._input_watch: select.poll | None = None
        #: takes every chunk as it arrives instead of the queue (:meth:`Transport.send_delivering`)
        self._receiver: Receiver | None = None
        #: ``loop.create_future`` of the connection's loop (``future_factory``): asyncio makes
        #: protocols inside the loop they serve
        self._loop = loop = asyncio.get_running_loop()
        self._new_future: Callable[[], asyncio.Future[Any]] = future_factory(loop)
        #: the loop's deadline heap, and this connection's entry for it (held weakly there),
        #: looked up and made once rather than on every arming
        self._deadlines = deadlines_of(loop)
        self._timer_entry: weakref.WeakMethod[Callable[[float], None]] = weakref.WeakMethod(
            self._on_timer
        )

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._flow = transport

    def _push(self, data: bytes) -> None:
        receiver = self._receiver
        if receiver is not None:
            receiver.chunk_received(data)
            return
        counters = self.counters
        queued = counters.queued + len(data)
        if queued > self.max_queued:
            if self._drop_when_full:
                counters.dropped += 1
                counters.dropped_bytes += len(data)
                return
            if not self._paused and self._flow is not None:
                self._paused = True
                counters.pauses += 1
                self._flow.pause_reading()  # type: ignore[attr-defined]
        counters.queued = queued
        if queued > counters.peak:
            counters.peak = queued
        self.arrived = self._loop.time()
        self._chunks.append(data)
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def _fail(self, exc: BaseException) -> None:
        if self._closed_exc is None:
            self._closed_exc = exc
        receiver = self._receiver
        if receiver is not None:
            self._receiver = None
            self._deadline = None
            receiver.receive_failed(self._lost())
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def _next_chunk(self, join: bool, deadline: float | None = None) -> bytes:
        chunks = self._chunks
        while not chunks:
            if self._closed_exc is not None:
                raise self._lost()
            self._waiter = waiter = self._new_future()
            if deadline is not None:
                self._deadline = deadline
                # One timer serves consecutive waits: it is re-armed only for an earlier
                # deadline (here) or, when it fires, for a later one (``_on_timer``). A fresh
                # timer per read cost a TimerHandle, a heap push and a cancel on every request.
                if not self._timer or self._timer_at > deadline:
                    self._arm(deadline)
            try:
                await waiter
            finally:
                self._waiter = None
                self._deadline = None
        if join and len(chunks) > 1:
            data = b"".join(chunks)
            chunks.clear()
        else:
            data = chunks.popleft()
        self._taken(len(data))
        return data

    def _lost(self) -> ConnectionLost:
        return ConnectionLost(f"connection to {self._peer} lost: {self._closed_exc}")

    def _taken(self, n: int) -> None:
        """``n`` queued bytes were handed to the reader: resume reading once the queue is empty
        (not at the first byte below the limit, which would pause again at once)."""
        counters = self.counters
        counters.queued -= n
        if self._paused and not self._chunks:
            self._paused = False
            flow = self._flow
            if flow is not None and not flow.is_closing():
                flow.resume_reading()  # type: ignore[attr-defined]

    def _arm(self, when: float) -> None:
        # on the loop's shared deadline heap (deadlines.py); an entry armed before is left
        # to come due and be ignored (``_on_timer`` compares its time with ``_timer_at``)
        self._timer = True
        self._timer_at = when
        self._deadlines.call_weak(when, self._timer_entry)

    def _on_timer(self, when: float) -> None:
        """A timer armed for ``when`` fired: if it is the current one, expire the current wait
        or delivery if its deadline is due, re-arm for it if it is later, and lapse if nobody
        waits with a deadline."""
        if not self._timer or when != self._timer_at:
            return  # replaced by an earlier one, or lapsed
        self._timer = False
        deadline, waiter, receiver = self._deadline, self._waiter, self._receiver
        if deadline is None or (receiver is None and (waiter is None or waiter.done())):
            return
        if deadline > when:
            self._arm(deadline)
        elif self._input_pending(deadline):
            # Bytes (or the end of the stream) wait in the kernel: the loop was held up past
            # the deadline and has not run the data callback yet. The peer was not silent, so
            # the loop first takes what waits; this timer looks again just after.
            self._arm(self._loop.time() + _INPUT_GRACE)
        elif receiver is not None:
            self._receiver = None
            self._deadline = None
            receiver.receive_failed(TimeoutError())
        else:
            waiter.set_exception(TimeoutError())  # type: ignore[union-attr]  # checked above

    def _input_pending(self, deadline: float) -> bool:
        """Whether the kernel holds input for this connection at an expired ``deadline`` that
        has not already waited :data:`_MAX_DEFERRALS` times for it (a descriptor that stays
        readable without the loop reading it must not hold a deadline off for ever)."""
        if self._deferred_for != deadline:
            self._deferred_for, self._deferrals = deadline, 0
        if self._deferrals >= _MAX_DEFERRALS or self._flow is None:
            return False
        watch = self._input_watch
        if watch is None:
            watch = self._input_watch = watch_input(self._flow)
            if watch is None:
                return False
        try:
            waiting = bool(watch.poll(0))
        except OSError:
            return False
        if waiting:
            self._deferrals += 1
        return waiting


#: seconds an expired deadline waits for input the kernel holds to reach the loop, and how many
#: times in a row: one loop pass takes it (the data callbacks run before the timers)
_INPUT_GRACE = 0.001
_MAX_DEFERRALS = 8


class ProtocolTransport(Transport):
    """What TCP, UDP and serial share: an asyncio transport plus a :class:`QueueProtocolMixin`.

    Subclasses implement ``open``, setting ``_transport``, ``_protocol`` and ``_send`` (through
    :meth:`_opened`); ``_join`` says whether queued chunks may be merged on read: yes for byte
    streams, never for datagrams.
    """

    _join = True

    def __init__(self, peer: str) -> None:
        self.peer = peer
        self._transport: asyncio.BaseTransport | None = None
        self._protocol: QueueProtocolMixin | None = None
        #: the open connection's send: the asyncio transport's ``write`` (``sendto``) itself,
        #: or that with the tap's record in front (:meth:`_opened`); ``write`` calls it only
        #: while a transport is open
        self._send: Callable[[bytes], None] = _not_open
        #: records this transport's connections (:meth:`record_to`), besides any ``capturing``
        self._tap: Tap | None = None
        #: a poll object watching the socket while open (:func:`watch_socket`); None when closed
        #: or not a socket (serial)
        self._watch: select.poll | None = None

    def quiet(self) -> bool:
        """Open, no chunk queued, and the kernel holds nothing for the socket: the ``poll`` of
        :meth:`input_waiting`, asked here directly (once per polled request, and this method
        already holds what ``input_waiting`` would look up again)."""
        watch = self._watch
        if watch is None:  # closed (``abort``/``aclose`` drop it first), or not a socket
            return False
        protocol = self._protocol
        if (
            protocol._chunks  # type: ignore[union-attr]  # set with the watch
            or protocol._closed_exc is not None  # type: ignore[union-attr]
            or self._transport.is_closing()  # type: ignore[union-attr]
        ):
            return False
        try:
            return not watch.poll(0)
        except OSError:
            return False

    def input_waiting(self) -> bool:
        """Ask the kernel (one ``poll`` with timeout 0) whether the socket has anything the loop
        has not handled yet: received bytes or datagrams (an empty one too), the peer's end of
        stream, an error.

        The descriptor is ours until ``connection_lost`` has run (which sets ``_closed_exc``);
        after that, or without a watched socket, the answer is "maybe" (``True``).
        """
        watch, protocol = self._watch, self._protocol
        if watch is None or protocol is None or protocol._closed_exc is not None:
            return True
        try:
            return bool(watch.poll(0))
        except OSError:
            return True

    def send_delivering(self, data: bytes, receiver: Receiver, timeout: float) -> None:
        self.write(data)
        protocol = self._protocol
        # the receiver, with its deadline on the connection's one timer (as a wait in
        # ``_next_chunk`` arms it)
        protocol._receiver = receiver  # type: ignore[union-attr]
        protocol._deadline = deadline = protocol._loop.time() + timeout  # type: ignore[union-attr]
        if not protocol._timer or protocol._timer_at > deadline:  # type: ignore[union-attr]
            protocol._arm(deadline)  # type: ignore[union-attr]

    def stop_delivery(self) -> None:
        protocol = self._protocol
        if protocol is not None:
            protocol._receiver = None
            protocol._deadline = None

    @property
    def is_open(self) -> bool:
        return (
            self._transport is not None
            and self._protocol is not None
            and self._protocol._closed_exc is None
            and not self._transport.is_closing()
        )

    def record_to(self, tap: Tap | None) -> None:
        """Record this transport's connections in ``tap`` from the next ``open`` on (None:
        stop recording them); a ``capturing`` block records them as well."""
        self._tap = tap

    @staticmethod
    async def _close_flushed(
        transport: asyncio.BaseTransport, protocol: QueueProtocolMixin, bound: float = 1.0
    ) -> None:
        """Close ``transport`` and wait (at most ``bound`` seconds) until it has ended, so
        what was written reaches the peer first: asyncio flushes a transport's write buffer
        before it ends it. A peer that never lets it end (no FIN answered, a line that
        takes nothing) is cut off by an abort."""
        transport.close()
        try:
            async with asyncio.timeout(bound):
                while protocol._closed_exc is None:
                    try:
                        await protocol._next_chunk(join=True)
                    except ConnectionLost:
                        break
        except TimeoutError:
            transport.abort()  # type: ignore[attr-defined]

    def _opened(
        self,
        transport: asyncio.BaseTransport,
        protocol: QueueProtocolMixin,
        send: Callable[[bytes], None],
    ) -> None:
        """Keep an opened connection: its transport, protocol and send (recorded when the
        protocol is a tapped one)."""
        self._transport, self._protocol = transport, protocol
        wire = protocol.wire
        self._send = send if wire is None else recorded_send(send, wire)

    def write(self, data: bytes) -> None:
        # ``is_open`` spelled out: this runs once per request
        transport = self._transport
        if (
            transport is None
            or self._protocol._closed_exc is not None  # type: ignore[union-attr]  # set together
            or transport.is_closing()
        ):
            raise ConnectionLost(f"not connected to {self.peer}")
        self._send(data)

    def read(self, deadline: float | None = None) -> Coroutine[Any, Any, bytes]:
        # Not ``async``: handing out the protocol's coroutine saves a coroutine frame per read.
        if self._protocol is None:
            raise ConnectionLost(f"not connected to {self.peer}")
        return self._protocol._next_chunk(self._join, deadline)

    @property
    def arrived(self) -> float | None:
        protocol = self._protocol
        return protocol.arrived if protocol is not None else None

    def take_received(self) -> list[bytes]:
        protocol = self._protocol
        if protocol is None or not protocol._chunks:
            return []
        chunks = list(protocol._chunks)
        protocol._chunks.clear()
        protocol._taken(protocol.counters.queued)
        return chunks

    @property
    def counters(self) -> ReceiveCounters:
        """Receive-queue counters of the current connection (fresh ones when closed)."""
        protocol = self._protocol
        return protocol.counters if protocol is not None else ReceiveCounters()

    def abort(self) -> None:
        transport = self._transport
        self._transport = None
        self._protocol = None
        self._watch = None
        if transport is not None:
            transport.abort()  # type: ignore[attr-defined]


def _not_open(data: bytes) -> None:
    raise ConnectionLost("not connected")


#: what makes a socket "have something for the loop": data, end of stream, an error
_READABLE = (
    getattr(select, "POLLIN", 0)
    | getattr(select, "POLLPRI", 0)
    | getattr(select, "POLLRDHUP", 0)
    | getattr(select, "POLLERR", 0)
    | getattr(select, "POLLHUP", 0)
)


def watch_input(
    transport: asyncio.BaseTransport, kinds: tuple[str, ...] = ("socket", "serial", "pipe")
) -> select.poll | None:
    """A ``poll`` object on the descriptor the transport reads: a socket, a serial port
    (pyserial-asyncio's ``serial``) or a pipe or pseudo-terminal (``pipe``), the first of
    ``kinds`` it has; None where it has none or there is no ``poll``."""
    if not hasattr(select, "poll"):
        return None
    for kind in kinds:
        source = transport.get_extra_info(kind)
        if source is not None:
            try:
                fileno = source.fileno()
            except (AttributeError, OSError, ValueError):
                return None
            watch = select.poll()
            watch.register(fileno, _READABLE)
            return watch
    return None


def watch_socket(transport: asyncio.BaseTransport) -> select.poll | None:
    """A ``poll`` object on the transport's socket, for ``quiet``/``input_waiting``; None
    where there is no socket or no ``poll`` (those then always take the general path)."""
    return watch_input(transport, ("socket",))


async def open_with_timeout(peer: str, coro: Awaitable[T], timeout: float | None) -> T:
    """Await a connect coroutine with a deadline, mapping failures to plcstack errors."""
    try:
        async with asyncio.timeout(timeout):
            return await coro
    except TimeoutError:
        raise PlcTimeout(f"connect to {peer} timed out after {timeout} s") from None
    except ConnectionRefusedError:
        # asyncio's own text ("Connect call failed ('10.0.0.5', 5000)") repeats the address and
        # hides the one fact the refusal carries: the host is up, the port is not served
        raise ConnectFailed(
            f"cannot connect to {peer}: connection refused, nothing listens on that port "
            "(wrong port, the module's connection not open, or the simulator not running)"
        ) from None
    except OSError as exc:
        raise ConnectFailed(f"cannot connect to {peer}: {exc.strerror or exc}") from None
