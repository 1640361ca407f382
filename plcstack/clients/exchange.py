"""Request/response clients (E71, S5-LAN, FETCH/WRITE): one exchange at a time, two drivers.

A :class:`RequestClient` sends a request and decodes its answer with a Sans-IO codec
(``send``/``receive_data``/``next_event``), under the failure policy of :class:`Client`. The
exchange has two drivers over the same steps (``_take_chunk``, ``_answer_complete``,
``_exchange_failed``):

* :meth:`RequestClient.exchange` awaits the answer's chunks (every request of the API);
* a prepared read (E71's :class:`~plcstack.clients.e71_lane.WordReadLane`, behind
  ``Client.start_read``) is handed them by the transport as they arrive
  (``Transport.send_delivering``) and calls back: no coroutine, no task step and no future per
  request, for the poller's scans of thousands of PLCs (``poll/scanner.py``). It takes the
  plain answer with the codec's own quick step and hands anything else to the callback steps
  here (``_x_adopt``, ``chunk_received``, ``receive_failed``), which decide with the steps
  ``exchange`` uses.

The two cannot decide differently because they share every decision; tests/test_callback_exchange.py
compares them on the same peers.
"""

from __future__ import annotations

import asyncio
import logging
from abc import abstractmethod
from collections.abc import Callable
from typing import Any, Generic, Protocol, TypeVar, overload

from plcstack.clients.base import Client
from plcstack.codecs._common import NEED_DATA
from plcstack.diagnose import Failure
from plcstack.errors import ConnectionLost, PlcError, PlcTimeout, RemoteProtocolError

__all__ = ["ClientCodec", "RequestClient"]

_log = logging.getLogger(__name__)

#: the Python type of a ``finish`` result
T = TypeVar("T")


class ClientCodec(Protocol):
    """The client role of a request/response Sans-IO codec (E71, S5-LAN, FETCH/WRITE)."""

    def send(self, request: Any) -> bytes: ...

    def receive_data(self, data: bytes) -> None: ...

    def next_event(self) -> Any: ...


E = TypeVar("E")


class RequestClient(Client, Generic[E]):
    """A client whose codec is request/response with ``send``/``receive_data``/``next_event``."""

    codec: ClientCodec

    #: the codec has ``take_answer(chunk)``: the whole answer to the one pending request from
    #: one chunk in one step, or None with nothing taken (see ``exchange``; E71 binary TCP)
    quick_answers = False

    #: True: always let the event loop run once before a request (the general path of the
    #: check for unsolicited bytes), even where the transport could ask the OS instead. Tests
    #: set it to compare both paths; nothing else needs to.
    stale_check_needs_loop_pass = False

    @abstractmethod
    def new_codec(self) -> ClientCodec:
        """A fresh client-role codec for a new connection."""

    def connection_made(self) -> None:
        self.codec = self.new_codec()
        self._settled = True

    #: the codec holds nothing undecoded: a fresh one, or the last exchange ended with
    #: ``_check_nothing_follows`` passing
    _settled = False

    @overload
    async def exchange(
        self, request: Any, what: str, *, is_write: bool, timeout: float | None = None
    ) -> E: ...

    @overload
    async def exchange(
        self,
        request: Any,
        what: str,
        *,
        is_write: bool,
        timeout: float | None = None,
        finish: Callable[[E, str], T],
    ) -> T: ...

    async def exchange(
        self,
        request: Any,
        what: str,
        *,
        is_write: bool,
        timeout: float | None = None,
        finish: Callable[[E, str], Any] | None = None,
    ) -> Any:
        """Send one request and return the codec's reply event (or ``finish(event, what)``).

        Holds the single-flight lock, (re)connects when needed, and turns every failure into a
        bound :class:`PlcError`. On a deadline or malformed reply the connection is closed so
        nothing stale can be read later. A write is never retried here.

        ``finish`` turns the event into the caller's result after the lock is released (it
        must not await): a client's ``read`` can then hand out this coroutine itself instead
        of awaiting it in one of its own, one coroutine fewer per request on the polling path.
        """
        flight = self._lock
        if not flight.try_acquire():  # taken at once when free: no coroutine
            await flight.acquire()
        try:
            transport = self.transport
            # Anything that arrived since the last answer (a duplicated answer, the rest of a
            # too-long one, bytes from a confused peer) would otherwise be decoded as the answer
            # to this request. Without a transaction id the only safe reaction is a fresh
            # connection before sending. Bytes the OS holds but the loop has not delivered yet
            # need two loop passes: in the first, asyncio's selector finds them and queues the
            # reader *behind* this task; in the second, the reader has run. A transport that can
            # ask the OS (TCP: one ``poll``) and hears "open, nothing queued, nothing waits"
            # (``quiet``), with a codec that holds nothing, spares the request all of it (fast
            # path; tests/test_fleet_paths.py compares the two).
            if self.stale_check_needs_loop_pass or not self._settled or not transport.quiet():
                if not transport.is_open:
                    await self._ensure_open(what)
                    transport = self.transport
                if self.stale_check_needs_loop_pass or transport.input_waiting():
                    await asyncio.sleep(0)
                    await asyncio.sleep(0)
                stale = self._unsolicited_input()
                if stale is not None or not transport.is_open:
                    if stale is not None:
                        _log.warning("%s: %s; reconnecting before %s", self.name, stale, what)
                        self.stats.errors += 1
                    self._drop()
                    await self._ensure_open(what)
                    transport = self.transport
            deadline = self.timeout if timeout is None else timeout
            try:
                event = self._send_request(request)
                if event is NEED_DATA:
                    expires = asyncio.get_running_loop().time() + deadline
                    read, take = transport.read, self._take_chunk
                    while event is NEED_DATA:
                        event = take(await read(expires))
            except asyncio.CancelledError:
                # The caller gave up (wait_for, a cancelled task) with the answer maybe still on
                # its way: it must die with the connection, or the codec (still expecting it)
                # would refuse or mis-assign the next request.
                self._drop()
                raise
            except (TimeoutError, PlcError) as exc:
                raise self._exchange_failed(exc, what, is_write, deadline) from None
        finally:
            flight.release()

        # every failure above raised: ``event`` is the answer
        return event if finish is None else finish(event, what)

    # -- the steps of one exchange, shared by both drivers ---------------------------------
    #
    # ``exchange`` awaits the chunks of an answer; the callback driver is handed them by the
    # transport (``send_delivering``). Both decode, settle and fail through the same steps
    # below, so the two paths cannot decide differently (tests/test_callback_exchange.py
    # compares them).

    #: the exchange in progress: what every chunk of its answer is and was (the first alone,
    #: then all in a list: the failure path's diagnosis), whether a byte of it left this host,
    #: and whether its first chunk may be taken whole (``take_answer``)
    _x_first = b""
    _x_chunks: list[bytes] | None = None
    _x_sent = False
    _x_quick = False

    def _send_request(self, request: Any) -> Any:
        """Count and send ``request`` on a connection checked for stale input: ``NEED_DATA``,
        or the answer an unsettled codec already holds (settled, as :meth:`_take_chunk`
        leaves it). Raises the transport's and the codec's errors."""
        self.stats.requests += 1
        self._x_first = b""
        self._x_chunks = None
        # A settled codec holds no bytes, so right after ``send`` it can only need data:
        # asking it (as an unsettled one must be asked) would cost a decode attempt.
        settled, self._settled = self._settled, False
        self._x_sent = False
        codec = self.codec
        self.transport.write(codec.send(request))
        self._x_sent = True
        # The usual case of a poll: the whole answer in one chunk and nothing more (see
        # ``_take_chunk``).
        self._x_quick = settled and self.quick_answers
        if settled:
            return NEED_DATA
        event = codec.next_event()
        return event if event is NEED_DATA else self._answer_complete(event)

    def _take_chunk(self, chunk: bytes) -> Any:
        """Feed one chunk of the answer: the answer event once it is complete (the codec then
        settled), else ``NEED_DATA``. Raises what the codec raises."""
        codec = self.codec
        if self._x_quick:
            self._x_quick = False
            # ``take_answer`` decides exactly as feeding the chunk, decoding and finding
            # nothing after it would, or takes nothing and says None (the general decoding
            # below then runs as before). Only codecs with the method set ``quick_answers``.
            quick = codec.take_answer(chunk)  # type: ignore[attr-defined]
            if quick is not None:
                self._answer_taken()
                return quick
        chunks = self._x_chunks
        if chunks is not None:
            chunks.append(chunk)
        elif self._x_first:
            self._x_chunks = [self._x_first, chunk]
        else:
            self._x_first = chunk
        codec.receive_data(chunk)
        event = codec.next_event()
        return event if event is NEED_DATA else self._answer_complete(event)

    def _answer_complete(self, event: Any) -> Any:
        self._check_nothing_follows(self.codec)
        self._answer_taken()
        return event

    def _answer_taken(self) -> None:
        """The codec gave the whole answer and holds nothing after it: it is settled, and the
        connection has proven itself (the backoff starts over)."""
        self._settled = True
        if self._unproven:
            self._answered()

    def _exchange_failed(
        self, exc: TimeoutError | PlcError, what: str, is_write: bool, deadline: float
    ) -> PlcError:
        """The bound error for a failure of the exchange in progress, under the failure policy
        (:meth:`request_failed`) where the connection can no longer be trusted."""
        if isinstance(exc, TimeoutError | ConnectionLost | RemoteProtocolError):
            reply = b"".join(self._x_chunks or (self._x_first,))
            failure: Failure
            if isinstance(exc, TimeoutError):
                failure = "timeout"
                exc = PlcTimeout(f"no complete answer within {deadline:g} s, connection closed")
            else:
                failure = "closed" if isinstance(exc, ConnectionLost) else "malformed"
            return self.request_failed(
                exc, failure, reply, what, is_write=is_write, sent=self._x_sent
            )
        self.stats.errors += 1
        return exc.bind(plc=self.name, request=what)

    # -- the callback driver ------------------------------------------------------------------
    # A prepared read (E71's ``WordReadLane``, ``clients/e71_lane.py``) starts an exchange
    # without awaiting (the transport hands the answer's chunks to it: ``send_delivering``)
    # and takes a plain answer itself. Anything else it hands to the steps below (``_x_adopt``),
    # which decide with the steps ``exchange`` uses and call its ``done`` exactly once.

    #: the callback exchange in progress (always a read: ``Client.start_read``): its
    #: ``done``, ``finish``, text and deadline; ``_x_done`` is None when none is
    _x_done: Callable[[Any], None] | None = None
    _x_finish: Callable[[Any, str], Any] | None = None
    _x_what = ""
    _x_deadline = 0.0

    def _x_adopt(self, finish: Callable[[Any, str], Any], what: str, *, sent: bool) -> None:
        """Take over a callback exchange that a prepared read started (``_x_done`` set, the
        request counted as ``_send_request`` counts it, the codec unsettled), in the state
        ``_send_request`` would have left: from here on the steps below decide. ``sent``:
        whether the request was handed to the transport. Its quick step (``take_answer``) is
        spent: the prepared read tried it on the first chunk, if one came."""
        self._x_finish, self._x_what = finish, what
        self._x_deadline = self.timeout
        self._x_first = b""
        self._x_chunks = None
        self._x_sent = sent
        self._x_quick = False

    def chunk_received(self, data: bytes) -> None:
        """A chunk of the answer to the callback exchange, from the prepared read that
        started it (the transport's :class:`~plcstack.transports.base.Receiver`)."""
        try:
            event = self._take_chunk(data)
        except Exception as exc:
            self._x_failed(exc)
            return
        if event is not NEED_DATA:
            self._x_answered(event)

    def receive_failed(self, exc: Exception) -> None:
        """The callback exchange's deadline passed or its connection ended (from the prepared
        read that started it)."""
        self._x_failed(exc)

    def _x_end(self) -> Callable[[Any], None]:
        """End the callback exchange in flight: no longer in flight, its receiver detached,
        the lock released (a waiter it is handed to runs in a later loop pass). Its ``done``.
        """
        done = self._x_done
        self._x_done = None
        self.transport.stop_delivery()
        self._lock.release()
        return done  # type: ignore[return-value]  # callers check or know it is in flight

    def _x_answered(self, event: Any) -> None:
        done = self._x_end()
        try:
            result = self._x_finish(event, self._x_what)  # type: ignore[misc]  # set with done
        except Exception as exc:  # the PLC's error code, bound (as ``exchange`` raises it)
            result = exc
        done(result)

    def _x_failed(self, exc: Exception) -> None:
        if self._x_done is None:
            return  # abandoned meanwhile
        done = self._x_end()
        error: Exception
        if isinstance(exc, TimeoutError | PlcError):
            is_write = False  # a callback exchange is a read
            error = self._exchange_failed(exc, self._x_what, is_write, self._x_deadline)
        else:  # a bug in a codec: what it left behind cannot be trusted
            self._drop()
            error = exc
        done(error)

    def abandon_exchange(self) -> None:
        if self._x_done is not None:
            self._x_end()
            self._drop()

    @staticmethod
    def _check_nothing_follows(codec: ClientCodec) -> None:
        """An answer that arrived together with more bytes (a second answer, or one longer than
        the request allows) cannot be trusted: without a transaction id there is no telling
        which part belongs to this request. Raises :class:`RemoteProtocolError`."""
        try:
            extra = codec.next_event()
        except RemoteProtocolError as exc:
            raise RemoteProtocolError(
                f"the answer came with more bytes than the request asks for ({exc.message}); "
                "not trusted, connection closed"
            ) from None
        if extra is not NEED_DATA:
            raise RemoteProtocolError(
                f"the answer was followed by a second one ({type(extra).__name__}); "
                "not trusted, connection closed"
            )

    def _unsolicited_input(self) -> str | None:
        """Feed bytes received between requests to the idle codec: ``None`` if they were only
        what the protocol allows there (e.g. MK life acks), else what was wrong with them."""
        received = self.transport.take_received()
        if not received and self._settled:
            # The last exchange left the codec with nothing to say (``_check_nothing_follows``)
            # and nothing came since: asking it again would answer NEED_DATA.
            return None
        codec = self.codec
        try:
            for chunk in received:
                codec.receive_data(chunk)
            event = codec.next_event()
        except PlcError as exc:
            return f"unsolicited data between requests ({exc.message})"
        if event is NEED_DATA:
            return None
        return f"unsolicited {type(event).__name__} between requests"

    def count_error(self) -> None:
        """Count a PLC error response decoded by the subclass (the reply itself was fine)."""
        self.stats.errors += 1
