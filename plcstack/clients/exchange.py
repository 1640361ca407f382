"""Request/response clients (E71, S5-LAN, FETCH/WRITE): one exchange at a time, one driver.

A :class:`RequestClient` sends a request and decodes its answer with a Sans-IO codec
(``send``/``receive_data``/``next_event``), under the failure policy of :class:`Client`.

Every request runs through one :class:`Exchange`: the object that owns the state of the
request in flight (the answer's chunks so far, whether the request left this host, the codec's
quick step) and is the transport's :class:`~plcstack.transports.base.Receiver` for its answer
(``Transport.send_delivering``). It decodes, settles and fails through one set of steps, and
calls ``done`` once with the result or the bound error. Its two callers differ only in how they
wait:

* :meth:`RequestClient.exchange` (every request of the API) takes the lock, checks the
  connection, starts the exchange and awaits a future that ``done`` resolves;
* :meth:`RequestClient.start_exchange` (the poller's scans, through ``Client.start_read``)
  starts it only when nothing needs waiting (lock free, connection quiet, codec settled) and
  hands it the scan's callback: no coroutine, no task step and no future per request.

The codec's quick step (``take_words``/``take_answer``: the whole normal answer from one chunk,
or nothing taken) is the exchange's first step on a settled connection; anything else goes
through ``receive_data``/``next_event``.
"""

from __future__ import annotations

import asyncio
import logging
from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar, overload

from plcstack.clients.base import Client
from plcstack.clients.flight import SingleFlight
from plcstack.codecs._common import NEED_DATA
from plcstack.diagnose import Failure
from plcstack.errors import ConnectionLost, PlcError, PlcTimeout, RemoteProtocolError

__all__ = ["ClientCodec", "Exchange", "Job", "RequestClient"]

_log = logging.getLogger(__name__)

#: the Python type of a ``finish`` result
T = TypeVar("T")


class ClientCodec(Protocol):
    """The client role of a request/response Sans-IO codec (E71, S5-LAN, FETCH/WRITE)."""

    def send(self, request: Any) -> bytes: ...

    def receive_data(self, data: bytes) -> None: ...

    def next_event(self) -> Any: ...


E = TypeVar("E")

#: what ``done`` receives: the result, or the exception the request ends with
Done = Callable[[Any], None]


@dataclass(frozen=True, slots=True)
class Job:
    """What one exchange sends and how its answer is finished: a plain record, built per
    request, or once for a read a client prepares (a poller sends the same reads every scan).

    ``finish(event, what)`` turns the answer event into the caller's result (it may raise the
    PLC's error code); ``words``: the result is the words of a 01H read, which the codec's
    quick step hands out without the event (``take_words``)."""

    request: Any
    what: str
    finish: Callable[[Any, str], Any] | None = None
    is_write: bool = False
    words: bool = False


def _nothing(result: Any) -> None:
    """The ``done`` of an exchange that has none in flight."""


class Exchange:
    """The request in flight on one connection of a :class:`RequestClient`, and its answer's
    :class:`~plcstack.transports.base.Receiver`. One per client, reused by each request (the
    client's lock lets one be in flight), so a request allocates nothing here.

    :meth:`start` sends; the transport hands each chunk to :meth:`chunk_received` and a
    deadline or a lost connection to :meth:`receive_failed`; the exchange then calls its
    ``done`` exactly once, unless :meth:`abandon` ends it first.
    """

    __slots__ = (
        "_chunks",
        "_client",
        "_deadline",
        "_done",
        "_first",
        "_job",
        "_lock",
        "_quick",
        "_sent",
        "_take_answer",
        "_take_words",
        "_waiter",
        "resolve",
        "settled",
    )

    def __init__(self, client: RequestClient[Any], lock: SingleFlight) -> None:
        self._client = client
        self._lock = lock
        #: the codec holds nothing undecoded: a fresh one, or the last answer was taken whole
        #: with nothing after it
        self.settled = False
        self._done: Done | None = None
        self._job = Job(None, "")
        self._deadline = 0.0
        #: the answer so far: its first chunk alone, then every chunk in a list (kept for the
        #: failure path's diagnosis)
        self._first = b""
        self._chunks: list[bytes] | None = None
        #: whether a byte of the request left this host
        self._sent = False
        #: whether the next chunk may be taken whole by the codec's quick step
        self._quick = False
        self._take_answer: Callable[[bytes], Any] | None = None
        self._take_words: Callable[[bytes], Any] | None = None
        #: the future an awaited exchange waits on (:meth:`RequestClient.exchange`)
        self._waiter: asyncio.Future[Any] | None = None
        #: bound once: the ``done`` of an awaited exchange
        self.resolve: Done = self._resolve

    def connected(self, codec: ClientCodec) -> None:
        """A fresh codec for a new connection, with or without the one-step decoding of a
        whole normal answer (``take_answer``, ``take_words``: E71; they take nothing where
        the answer cannot be taken whole, over UDP or in ASCII)."""
        self.settled = True
        self._take_answer = getattr(codec, "take_answer", None)
        self._take_words = getattr(codec, "take_words", None)

    @property
    def in_flight(self) -> bool:
        return self._done is not None

    # -- the steps ------------------------------------------------------------------------------
    def start(self, job: Job, done: Done, timeout: float) -> None:
        """Send ``job.request`` (the client's lock held, the connection checked for stale
        input) and take its answer as it arrives; ``done`` is called once with the result
        (``job.finish(event, what)``, or the event) or with the bound error."""
        client = self._client
        self._job = job
        self._done = done
        self._deadline = timeout
        if self._first:  # the last answer's chunks, kept for a diagnosis that never came
            self._first = b""
            self._chunks = None
        client.stats.requests += 1
        # A settled codec holds no bytes, so right after ``send`` it can only need data.
        settled = self.settled
        self.settled = False
        self._quick = settled
        codec = client.codec
        try:
            client.transport.send_delivering(codec.send(job.request), self, timeout)
        except Exception as exc:
            self._sent = False  # nothing left this host
            self._failed(exc)
            return
        self._sent = True
        if settled:
            return
        try:
            # an unsettled codec may already hold the answer
            event = codec.next_event()
            if event is not NEED_DATA:
                self._answered(self._complete(event))
        except Exception as exc:
            self._failed(exc)

    def chunk_received(self, data: bytes) -> None:
        """A chunk of the answer (:class:`~plcstack.transports.base.Receiver`)."""
        try:
            if self._quick and self._take_words is not None:
                # The usual case of a poll: the whole normal answer in this one chunk and
                # nothing more. The codec decides exactly as feeding the chunk, decoding and
                # finding nothing after it would, or takes nothing (the general step below).
                self._quick = False
                if self._job.words:
                    words = self._take_words(data)
                    if words is not None:
                        self._taken()
                        self._end()(list(words))
                        return
                else:
                    event = self._take_answer(data)  # type: ignore[misc]  # set with words
                    if event is not None:
                        self._taken()
                        self._answered(event)
                        return
            event = self._take(data)
        except Exception as exc:
            self._failed(exc)
            return
        if event is not NEED_DATA:
            self._answered(event)

    def receive_failed(self, exc: Exception) -> None:
        """The deadline passed or the connection ended (:class:`Receiver`)."""
        self._failed(exc)

    def abandon(self) -> None:
        """End the exchange in flight, if any, without its ``done``; the connection is closed,
        since its answer may still come."""
        if self._done is not None:
            self._end()
            self._client.drop()

    def _take(self, chunk: bytes) -> Any:
        """Feed one chunk: the answer event once it is complete, else ``NEED_DATA``."""
        chunks = self._chunks
        if chunks is not None:
            chunks.append(chunk)
        elif self._first:
            self._chunks = [self._first, chunk]
        else:
            self._first = chunk
        codec = self._client.codec
        codec.receive_data(chunk)
        event = codec.next_event()
        return event if event is NEED_DATA else self._complete(event)

    def _complete(self, event: Any) -> Any:
        _check_nothing_follows(self._client.codec)
        self._taken()
        return event

    def _taken(self) -> None:
        """The codec gave the whole answer and holds nothing after it: it is settled, and the
        connection has proven itself (the backoff starts over)."""
        self.settled = True
        client = self._client
        if client.unproven:
            client.answered()

    def _end(self) -> Done:
        """No longer in flight: the receiver detached, the lock released (a waiter it is handed
        to runs in a later loop pass). Returns the ``done``."""
        done = self._done
        self._done = None
        self._client.transport.stop_delivery()
        self._lock.release()
        return done or _nothing

    def _answered(self, event: Any) -> None:
        done = self._end()
        job = self._job
        finish = job.finish
        if finish is None:
            done(event)
            return
        try:
            result = finish(event, job.what)
        except Exception as exc:  # the PLC's error code, bound
            result = exc
        done(result)

    def _failed(self, exc: Exception) -> None:
        if self._done is None:
            return  # abandoned meanwhile
        done = self._end()
        error: Exception
        if isinstance(exc, TimeoutError | PlcError):
            error = self._error(exc)
        else:  # a bug in a codec: what it left behind cannot be trusted
            self._client.drop()
            error = exc
        done(error)

    def _error(self, exc: TimeoutError | PlcError) -> PlcError:
        """The bound error for a failure of this exchange, under the failure policy
        (:meth:`Client.request_failed`) where the connection can no longer be trusted."""
        client = self._client
        job = self._job
        if isinstance(exc, TimeoutError | ConnectionLost | RemoteProtocolError):
            reply = b"".join(self._chunks or (self._first,))
            failure: Failure
            if isinstance(exc, TimeoutError):
                failure = "timeout"
                exc = PlcTimeout(
                    f"no complete answer within {self._deadline:g} s, connection closed"
                )
            else:
                failure = "closed" if isinstance(exc, ConnectionLost) else "malformed"
            return client.request_failed(
                exc, failure, reply, job.what, is_write=job.is_write, sent=self._sent
            )
        client.stats.errors += 1
        return exc.bind(plc=client.name, request=job.what)

    # -- the awaited exchange's future ----------------------------------------------------------
    def wait(self) -> asyncio.Future[Any]:
        """A future for the next exchange's result (its ``done`` is :attr:`resolve`)."""
        self._waiter = waiter = asyncio.get_running_loop().create_future()
        return waiter

    def _resolve(self, result: Any) -> None:
        waiter = self._waiter
        self._waiter = None
        if waiter is not None and not waiter.done():  # its task may have been cancelled
            waiter.set_result(result)


def _check_nothing_follows(codec: ClientCodec) -> None:
    """An answer that arrived together with more bytes (a second answer, or one longer than the
    request allows) cannot be trusted: without a transaction id there is no telling which part
    belongs to this request. Raises :class:`RemoteProtocolError`."""
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


class RequestClient(Client, Generic[E]):
    """A client whose codec is request/response with ``send``/``receive_data``/``next_event``."""

    codec: ClientCodec

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        #: the one exchange driver of this connection
        self.exchange_driver = Exchange(self, self._lock)

    @abstractmethod
    def new_codec(self) -> ClientCodec:
        """A fresh client-role codec for a new connection."""

    def connection_made(self) -> None:
        self.codec = codec = self.new_codec()
        self.exchange_driver.connected(codec)

    @overload
    async def exchange(
        self,
        request: Any,
        what: str,
        *,
        is_write: bool,
        timeout: float | None = None,
        words: bool = False,
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
        words: bool = False,
    ) -> T: ...

    async def exchange(
        self,
        request: Any,
        what: str,
        *,
        is_write: bool,
        timeout: float | None = None,
        finish: Callable[[E, str], Any] | None = None,
        words: bool = False,
    ) -> Any:
        """Send one request and return the codec's reply event (or ``finish(event, what)``).

        Holds the single-flight lock, (re)connects when needed, and turns every failure into a
        bound :class:`PlcError`. On a deadline or malformed reply the connection is closed so
        nothing stale can be read later. A write is never retried here. ``finish`` must not
        await; ``words``: see :meth:`Exchange.start`.
        """
        flight = self._lock
        if not flight.try_acquire():  # taken at once when free: no coroutine
            await flight.acquire()
        x = self.exchange_driver
        try:
            transport = self.transport
            # Anything that arrived since the last answer (a duplicated answer, the rest of a
            # too-long one, bytes from a confused peer) would otherwise be decoded as the answer
            # to this request. Without a transaction id the only safe reaction is a fresh
            # connection before sending. Bytes the OS holds but the loop has not delivered yet
            # need two loop passes: in the first, asyncio's selector finds them and queues the
            # reader *behind* this task; in the second, the reader has run. A transport that can
            # ask the OS (TCP: one ``poll``) and hears "open, nothing queued, nothing waits"
            # (``quiet``), with a codec that holds nothing, spares the request all of it.
            if not x.settled or not transport.quiet():
                if not transport.is_open:
                    await self._ensure_open(what)
                    transport = self.transport
                if transport.input_waiting():
                    await asyncio.sleep(0)
                    await asyncio.sleep(0)
                stale = self._unsolicited_input()
                if stale is not None or not transport.is_open:
                    if stale is not None:
                        _log.warning("%s: %s; reconnecting before %s", self.name, stale, what)
                        self.stats.errors += 1
                    self.drop()
                    await self._ensure_open(what)
            waiter = x.wait()
        except BaseException:
            flight.release()
            raise
        x.start(
            Job(request, what, finish, is_write, words),
            x.resolve,
            self.timeout if timeout is None else timeout,
        )
        try:
            result = await waiter
        except asyncio.CancelledError:
            # The caller gave up (wait_for, a cancelled task) with the answer maybe still on its
            # way: it must die with the connection, or the codec (still expecting it) would
            # refuse or mis-assign the next request.
            x.abandon()
            raise
        if isinstance(result, Exception):
            raise result
        return result

    def start_exchange(self, job: Job, done: Done) -> bool:
        """:meth:`exchange` of a read ``job`` without awaiting, when that needs no waiting
        (codec settled, connection quiet, lock free): ``True``, and ``done`` is later called
        once with the result or the error ``exchange`` would raise (it may run before this
        returns: a send that fails at once); else ``False`` with nothing sent or changed."""
        x = self.exchange_driver
        if not x.settled or not self.transport.quiet() or not self._lock.try_acquire():
            return False
        x.start(job, done, self.timeout)
        return True

    def abandon_exchange(self) -> None:
        self.exchange_driver.abandon()

    def _unsolicited_input(self) -> str | None:
        """Feed bytes received between requests to the idle codec: ``None`` if they were only
        what the protocol allows there (e.g. MK life acks), else what was wrong with them."""
        received = self.transport.take_received()
        if not received and self.exchange_driver.settled:
            # The last exchange left the codec with nothing to say and nothing came since:
            # asking it again would answer NEED_DATA.
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
