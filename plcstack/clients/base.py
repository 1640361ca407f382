"""What every protocol client shares: connection life cycle, single flight, deadlines, errors.

None of our protocols has a transaction id, so the only way to never mix up replies is one request
in flight per connection and a hard close when a deadline passes. That policy lives here once, and
each protocol client only says how to build a request and what its reply means.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from abc import abstractmethod
from collections.abc import AsyncIterator, Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self, TypeVar, overload

from plcstack.clients.flight import ConnectTurns, SingleFlight
from plcstack.clients.options import COMMON, Option, resolve
from plcstack.diagnose import Failure
from plcstack.durations import check_seconds
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    PlcError,
    ValueEncodeError,
)
from plcstack.logs import install_trace
from plcstack.resource import AsyncResource
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.url import PlcUrl
from plcstack.values import (
    BOOL,
    ByteOrder,
    Endian,
    ValueType,
    WordOrder,
    bits_of_points,
    value_type,
)

__all__ = [
    "Client",
    "ClientStats",
    "Failure",
    "Points",
    "Value",
    "as_points",
]

_log = logging.getLogger(__name__)

#: what ``read`` returns per point: ``int`` for words/bytes, ``bool`` for bits
Value = int | bool
#: the Python type of one value of a :class:`~plcstack.values.ValueType`
T = TypeVar("T")
#: what ``write`` takes: one point or a sequence of them
Points = int | bool | Sequence[int] | Sequence[bool]


def as_points(
    values: Points, *, plc: str | None = None, request: str | None = None
) -> Sequence[int] | Sequence[bool]:
    """``values`` as a sequence: a single int or bool (``plc.write("D100", 5)``) becomes a list
    of one; a list, tuple or range is returned unchanged for the client's own per-value checks.

    Anything else is a :class:`~plcstack.errors.ValueEncodeError` naming the value and its type,
    before any length or address is looked at: a float or ``None`` would otherwise surface as a
    bare ``TypeError``, and ``bytes``/``str`` would be written as one point per byte or
    character, which is never what a word write means (typed values go through ``write_as``).
    """
    if isinstance(values, int):
        return [values]
    if isinstance(values, str | bytes | bytearray | memoryview) or not isinstance(values, Sequence):
        hint = (
            "for text use write_as(address, string(N), ...)"
            if isinstance(values, str)
            else "for bytes pass a list of ints, one per point"
            if isinstance(values, bytes | bytearray | memoryview)
            else "for a float use write_as(address, FLOAT32 or KG, ...)"
            if isinstance(values, float)
            else "pass an int, a bool or a list of them"
        )
        raise ValueEncodeError(
            f"value {values!r} ({type(values).__name__}) cannot be written as points: write takes "
            f"an int, a bool or a sequence of them; {hint}",
            plc=plc,
            request=request,
        )
    return values


#: default request deadline in seconds; every client takes ``timeout=`` and ``?timeout=``
DEFAULT_TIMEOUT = 2.0
DEFAULT_CONNECT_TIMEOUT = 3.0

#: what a failed write says once any byte of it left this host: no reply means no knowledge
MAY_OR_MAY_NOT = "the write may or may not have been executed"
#: what a failed write says when it failed before a byte of it was sent
NOT_SENT = "the write was not sent, so nothing was written"


@dataclass
class ClientStats:
    """Counters a poller or a dashboard can read without wrapping every call."""

    requests: int = 0
    errors: int = 0
    timeouts: int = 0
    connects: int = 0
    connect_failures: int = 0


class Client(AsyncResource):
    """The API every protocol shares, so the CLI and the poller are protocol-agnostic.

    Use as ``async with plcstack.connect(url) as plc:``. A client reconnects by itself when a
    request finds the connection closed; while the PLC stays unreachable, reconnect attempts are
    spaced by jittered exponential backoff and requests in between fail at once with
    :class:`ConnectFailed` (saying when the next attempt is due) instead of piling up.
    """

    #: order of the points of a multi-point value (MELSEC: LITTLE, low word first; S5: BIG)
    word_order: ClassVar[WordOrder] = Endian.BIG
    #: order of two characters in a word (MELSEC: LITTLE, first character in the low byte)
    byte_order: ClassVar[ByteOrder] = Endian.BIG

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        connect_timeout: float = DEFAULT_CONNECT_TIMEOUT,
        backoff: Backoff | None = None,
    ) -> None:
        self.name = name
        self.transport = transport
        # the DEBUG frame trace (plcstack.frames.PROTOCOL); nothing at all on the path when off
        install_trace(transport, name, type(self).__module__.rpartition(".")[2])
        self.timeout = check_seconds("timeout", timeout, plc=name)
        self.connect_timeout = check_seconds("connect_timeout", connect_timeout, plc=name)
        self.backoff = backoff if backoff is not None else Backoff()
        self.stats = ClientStats()
        #: one request in flight per connection (see :mod:`.flight`)
        self._lock = SingleFlight()
        self._next_attempt = 0.0
        #: what the last failed connect (or unproven connection) said; "" after a connect
        self._backoff_detail = ""
        self._closed = False
        #: ``stats.requests`` when the connection was made: tells the failure path whether the
        #: request that failed was the first one on this connection (no cost on the hot path)
        self._requests_at_connect = 0
        #: the current connection has not yet produced one valid answer. Backoff is reset by
        #: the first valid answer, not by TCP getting in: a peer that accepts and then garbles
        #: or closes every time would otherwise be reconnected at full speed.
        self.unproven = True
        #: connections in a row that closed or garbled before one valid answer
        self._unproven_failures = 0
        #: no connection of this client has produced a valid answer yet. Only then does a peer
        #: that closes or stays silent on a first request hint at a wrong port or protocol;
        #: once the same URL answered, it is a PLC restarting or a network drop
        self.never_answered = True
        #: why requests fail fast until ``_next_attempt`` ("PLC unreachable", ...)
        self._backoff_reason = "PLC unreachable"
        #: shared by the clients of one poller (None: connect at once). A connect waits for a
        #: slot before its ``connect_timeout`` starts: when thousands of PLCs connect at the
        #: same time, the event loop's own backlog must not be what times them out.
        self.connect_turns: ConnectTurns | None = None

    # -- construction -----------------------------------------------------------------------
    #: this client's options, shared by the URL query and keywords (:mod:`.options`)
    OPTIONS: ClassVar[tuple[Option, ...]] = COMMON

    @classmethod
    def options_for(cls, url: PlcUrl) -> tuple[Option, ...]:
        """The options a URL of this client takes (AS511: serial line settings on serial)."""
        return cls.OPTIONS

    @classmethod
    def from_url(cls, url: PlcUrl, **options: object) -> Self:
        """Build from a parsed URL; keyword options override query options. Every option is
        checked by the one schema (:attr:`OPTIONS`): a bad one is an :class:`OptionError`."""
        return cls.create(url, resolve(cls.options_for(url), url, options))

    @classmethod
    def create(cls, url: PlcUrl, options: dict[str, Any]) -> Self:
        """Build from a URL and its resolved options (every name of :attr:`OPTIONS` present)."""
        raise NotImplementedError(f"{cls.__name__} cannot be built from a URL")

    #: fresh connections in a row that may close or garble before one valid answer before
    #: reconnects back off (see :meth:`request_failed`)
    UNPROVEN_FAILURES_BEFORE_BACKOFF = 2

    # -- life cycle -------------------------------------------------------------------------
    async def open(self) -> None:
        """Connect now (``async with`` does this); raises ``ConnectFailed`` or ``PlcTimeout``."""
        self._closed = False
        async with self._lock:
            await self._connect()

    async def aclose(self) -> None:
        self._closed = True
        await self.transport.aclose()

    async def aopen(self) -> None:
        await self.open()

    @contextlib.asynccontextmanager
    async def turn(self, deadline: float | None = None) -> AsyncIterator[None]:
        """The connection for the calling task alone, for several requests in a row.

        What a native face's request needs when it is more than one request (the value before
        a write, for the audit; a monitor registration and its monitor): nothing of anyone
        else's (a scan, a write from the north side) goes between them. Waits for the
        connection in arrival order like any request; raises ``TimeoutError`` when the event
        loop's time reaches ``deadline`` first, and then nothing was sent. Inside, only the
        calling task's requests go through; another task's wait until the turn ends.
        """
        await self._lock.hold(deadline)
        try:
            yield
        finally:
            self._lock.unhold()

    def __repr__(self) -> str:
        state = "open" if self.transport.is_open else "closed"
        return f"<{type(self).__name__} {self.name} {state}>"

    async def _connect(self) -> None:
        try:
            turns = self.connect_turns
            if turns is None:
                await self.transport.open(self.connect_timeout)
            else:
                async with turns.turn():
                    await self.transport.open(self.connect_timeout)
        except PlcError as exc:
            self.stats.connect_failures += 1
            exc.bind(plc=self.name, request="connect")
            self._back_off(exc.message, "PLC unreachable")
            _log.info("%s: connect failed: %s", self.name, exc.message)
            raise
        _log.info("%s: connected to %s", self.name, self.transport.peer)
        self.stats.connects += 1
        self._requests_at_connect = self.stats.requests
        self.unproven = True
        self._backoff_detail = ""
        self.connection_made()

    def _back_off(self, detail: str, reason: str) -> None:
        """Refuse reconnects until the backoff delay has passed; requests meanwhile fail at once
        with :class:`ConnectFailed` (nothing of them is sent) naming ``reason`` and ``detail``."""
        loop = asyncio.get_running_loop()
        self._next_attempt = loop.time() + self.backoff.next_delay()
        self._backoff_detail = detail
        self._backoff_reason = reason

    def answered(self) -> None:
        """The connection produced a valid answer: it works, so the backoff starts over.
        Callers test :attr:`unproven` first, keeping the hot path at one attribute read."""
        self.unproven = False
        self._unproven_failures = 0
        self.never_answered = False
        self.backoff.reset()

    async def _ensure_open(self, what: str) -> None:
        if self.transport.is_open:
            return
        if self._closed:
            raise ConnectionLost("client is closed", plc=self.name, request=what)
        loop = asyncio.get_running_loop()
        wait = self._next_attempt - loop.time()
        if wait > 0 and self._backoff_detail:
            raise ConnectFailed(
                f"{self._backoff_reason} ({self._backoff_detail}); "
                f"next reconnect attempt in {wait:.1f} s",
                plc=self.name,
                request=what,
            )
        await self._connect()

    def connection_made(self) -> None:
        """Hook: a (re)connect succeeded; reset per-connection codec state here."""

    def connection_dropped(self) -> None:
        """Hook: the connection was closed because of an error or a deadline."""

    def first_on_connection(self) -> bool:
        """Whether the request in flight is the first one on this connection (failure path)."""
        return self.stats.requests - self._requests_at_connect <= 1

    def first_ever(self) -> bool:
        """Whether the request in flight is the first on this connection and no connection
        before answered (failure path): only then is a close or silence evidence about the
        settings (a soak that cut connections saw "this port is probably not an E71" on PLCs
        that had answered thousands of requests)."""
        return self.never_answered and self.first_on_connection()

    def diagnose(self, failure: Failure, reply: bytes) -> str:
        """Hook for the failure path only: one plain-words sentence on what is probably
        misconfigured, judged from ``reply`` (every byte received for the failed request), or
        ``""`` when the evidence supports nothing. See :mod:`plcstack.diagnose`."""
        return ""

    def _hint(self, failure: Failure, reply: bytes) -> str:
        """``". Hint: ..."`` to end an error message with, or ``""``."""
        try:
            hint = self.diagnose(failure, reply)
        except Exception:  # a diagnosis must never replace the error it explains
            _log.exception("%s: diagnosis failed", self.name)
            return ""
        return f". Hint: {hint}" if hint else ""

    def drop(self) -> None:
        """Close the connection after a failure; the next request reconnects (failure and
        reconnect paths only: deadline, bad or stale bytes, cancel, peer gone)."""
        _log.info("%s: connection closed; the next request reconnects", self.name)
        self.transport.abort()
        self.connection_dropped()

    def request_failed(
        self,
        exc: PlcError,
        failure: Failure,
        reply: bytes,
        what: str,
        *,
        is_write: bool,
        sent: bool,
        drop: bool = True,
        outcome: str | None = None,
    ) -> PlcError:
        """The one failure policy of every client (request/response and AS511 alike) for a
        request that got no valid answer: count it, close the connection (``drop``; an AS511
        serial line resynchronises by silence instead), say for a write whether it may have
        been executed, add the diagnosis of ``reply`` (every byte received for the request),
        back off when a fresh connection never answered validly, and bind PLC and request.

        ``sent`` says whether any byte of the request left this host; ``outcome`` overrides the
        write wording when the protocol knows better (an AS511 acknowledgement). Returns the
        exception for the caller to raise.
        """
        self.stats.errors += 1
        if failure == "timeout":
            self.stats.timeouts += 1
        if drop:
            self.drop()
        hint = self._hint(failure, reply)
        if sent and failure != "timeout" and self.unproven and drop:
            # Closed or garbled before one valid answer on this connection. Once is a glitch
            # (the next request reconnects at once); again on the next fresh connection, and
            # the one after would most likely meet the same, so reconnects back off as after a
            # refused connect (a timeout already spaces attempts by its own deadline).
            self._unproven_failures += 1
            if self._unproven_failures >= self.UNPROVEN_FAILURES_BEFORE_BACKOFF:
                self._back_off(exc.message + hint, "no valid answer on the last connection")
        if is_write:
            exc.message += "; " + (outcome or (MAY_OR_MAY_NOT if sent else NOT_SENT))
        exc.message += hint
        return exc.bind(plc=self.name, request=what)

    # -- the API ----------------------------------------------------------------------------
    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        """``(area, index)`` of ``address``, such that point ``k`` of a read is ``index + k``.

        The poller merges tags of one PLC whose areas are equal into one request, so ``area``
        must capture everything that has to match (device code, DB number, unit); ``count`` lets a
        protocol refuse a span that cannot be one request. Raises :class:`AddressError`.
        """
        raise NotImplementedError(f"{type(self).__name__} does not support request merging")

    def address_at(self, area: Hashable, index: int) -> str:
        """The address string for ``(area, index)``: the inverse of :meth:`locate`."""
        raise NotImplementedError(f"{type(self).__name__} does not support request merging")

    def max_points(self, area: Hashable) -> int:
        """Most points of ``area`` one ``read`` sends as a single frame (the per-frame limit)."""
        raise NotImplementedError(f"{type(self).__name__} does not support request merging")

    def point_bits(self, area: Hashable) -> int:
        """Bits per point of ``area``: 1 for bit devices, 8 for byte areas, 16 for words.

        The poller needs it to know how many points an int32 or float32 tag spans. Part of the
        base (not an optional attribute) so a protocol with byte or bit areas cannot forget it
        silently; the default is right only for word-only protocols.
        """
        return 16

    @abstractmethod
    async def read(self, address: str, count: int = 1) -> list[int] | list[bool]:
        """Read ``count`` points from ``address``: ints for words/bytes, bools for bits."""

    #: whether :meth:`start_read` can say ``True`` at all: the poller runs the scans of a PLC
    #: whose client cannot on the PLC's task instead (one task step per scan, no task per scan)
    callback_reads: ClassVar[bool] = False

    def start_read(self, address: str, count: int, done: Callable[[Any], None]) -> bool:
        """Start ``read(address, count)`` without awaiting it, when that needs no waiting:
        ``True``, and ``done`` is later called once with what ``await read(...)`` returns or
        the exception it raises; else ``False`` and nothing happened (await :meth:`read`).

        The poller's path for thousands of reads a second (``RequestClient.start_exchange``). The
        default always says ``False``; a client says ``True`` only for reads it has already
        done once the general way.
        """
        return False

    def abandon_exchange(self) -> None:
        """Give up a read started by :meth:`start_read` and still in flight, if any, without
        its ``done`` being called; the connection is closed, as when an awaited read is
        cancelled."""

    @abstractmethod
    async def write(self, address: str, values: Points) -> None:
        """Write ``values`` (one point or a sequence) starting at ``address``; returns once the
        PLC confirmed it."""

    # -- typed values -----------------------------------------------------------------------
    def split_bit(self, address: str) -> tuple[str, int | None]:
        """``(word address, bit)`` for the family's bit-of-a-word notation (``D100.3``,
        ``DB10.DW5.3``), ``(address, None)`` otherwise. Raises :class:`AddressError` for a
        bit number the notation does not allow."""
        return address, None

    def _named_type(self, vtype: ValueType[T] | str, what: str) -> ValueType[T]:
        """``vtype`` itself, or the type a name (``"kg"``) stands for: one spelling of the
        value types for the CLI, the poll config and Python."""
        if not isinstance(vtype, str):
            return vtype
        try:
            return value_type(vtype)
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=what) from None

    def _value_span(
        self, address: str, vtype: ValueType[Any], count: int, what: str
    ) -> tuple[str, int | None, int, int]:
        """``(address to read, bit, point bits, points)`` for ``count`` values; nothing sent."""
        try:
            if not isinstance(vtype, ValueType):
                raise AddressError(f"{vtype!r} is not a value type (e.g. plcstack.values.INT16)")
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise AddressError(f"count must be a positive integer, not {count!r}")
            base, bit = self.split_bit(address)
            try:
                area, _ = self.locate(base, 1)
                bits = self.point_bits(area)
            except NotImplementedError:
                bits = 16
            if bit is not None:
                if vtype is not BOOL:
                    raise AddressError(f"a bit of a word ({address}) is read as BOOL")
                if bits <= 1 or bit >= bits:
                    raise AddressError(f"bit {bit} is not a bit of a {bits}-bit point")
                return base, bit, bits, -(-(bit + count) // bits)
            vtype.check_area(bits, address)
            return base, None, bits, count * vtype.points_per_value(bits)
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=what) from None

    @overload
    async def read_as(
        self,
        address: str,
        vtype: ValueType[T],
        count: None = None,
        *,
        word_order: WordOrder | None = None,
    ) -> T: ...

    @overload
    async def read_as(
        self,
        address: str,
        vtype: str,
        count: None = None,
        *,
        word_order: WordOrder | None = None,
    ) -> Any: ...

    @overload
    async def read_as(
        self,
        address: str,
        vtype: str,
        count: int,
        *,
        word_order: WordOrder | None = None,
    ) -> list[Any]: ...

    @overload
    async def read_as(
        self,
        address: str,
        vtype: ValueType[T],
        count: int,
        *,
        word_order: WordOrder | None = None,
    ) -> list[T]: ...

    async def read_as(
        self,
        address: str,
        vtype: ValueType[Any] | str,
        count: int | None = None,
        *,
        word_order: WordOrder | None = None,
    ) -> Any:
        """One value of ``vtype`` at ``address`` (``count`` omitted) or a list of ``count``.

        ``await plc.read_as("DB10.DW4", KG)`` is a ``float`` to mypy too; a bit of a word
        (``D100.3``, ``DB10.DW5.3``, ``M10.3``) reads as ``BOOL``. ``vtype`` may also be a type
        name as the CLI and the poll config spell it (``"kg"``, ``"int32"``, ``"string:8"``).
        Multi-point values use the PLC family's word order unless ``word_order`` is given. One
        request, like :meth:`read`.
        """
        n = 1 if count is None else count
        what = f"read {address} as {getattr(vtype, 'name', vtype)} x{n}"
        vtype = self._named_type(vtype, what)
        base, bit, bits, points = self._value_span(address, vtype, n, what)
        raw = await self.read(base, points)
        try:
            if bit is not None:
                values: list[Any] = bits_of_points(raw, bits, bit, n)
            else:
                order = word_order or self.word_order
                values = vtype.decode_many(raw, n, bits, order, self.byte_order)
        except PlcError as exc:
            raise exc.bind(plc=self.name, request=what) from None
        return values[0] if count is None else values

    async def write_as(
        self,
        address: str,
        vtype: ValueType[T] | str,
        value: T | list[T],
        *,
        word_order: WordOrder | None = None,
    ) -> None:
        """Write one value of ``vtype`` (or a ``list`` of values) from ``address`` on.

        ``vtype`` is a type or its name (``"float32"``). Every value is checked first: one that
        the type cannot hold (NaN as KG, 10000 as BCD16) raises
        :class:`~plcstack.errors.ValueEncodeError` and nothing is sent. A bit of a word is
        refused: it would be a read-modify-write racing the PLC program.
        """
        values: list[Any] = value if isinstance(value, list) else [value]
        what = f"write {address} as {getattr(vtype, 'name', vtype)} x{len(values)}"
        vtype = self._named_type(vtype, what)
        base, bit, bits, _ = self._value_span(address, vtype, max(1, len(values)), what)
        try:
            if not values:
                raise AddressError("no values to write")
            if bit is not None:
                raise AddressError(
                    f"{address} is a bit of a word: writing it would be a read-modify-write "
                    "that can undo a change the PLC makes in between; write the whole word"
                )
            order = word_order or self.word_order
            points = vtype.encode_many(values, bits, order, self.byte_order)
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=what) from None
        if bits <= 1:
            await self.write(base, [bool(p) for p in points])
        else:
            await self.write(base, [int(p) for p in points])
