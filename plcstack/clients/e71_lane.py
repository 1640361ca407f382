"""A checked E71 word read, prepared for the callback exchanges of a poller's scans.

A poller reads the same few addresses of every PLC ten times a second. Through the general
callback driver (``RequestClient.start_exchange`` until this module) each of those reads passed
through five layers (``start_read``, ``start_exchange``, ``_send_request``, ``_take_chunk``,
``_x_answered``), each keeping state for cases a poll almost never meets: which chunks came
(for the diagnosis of a failure), whether the request left the host, whether its answer may be
taken whole. At a thousand PLCs those bytecodes were what separated the poller from a raw
asyncio loop: perf put 19.1 against 9.7 us per request in the interpreter loop, against a
fused prototype that did only what the plain case needs.

A :class:`WordReadLane` is that plain case, kept with the client's cache of checked word reads
(one lane per address and count). :meth:`~WordReadLane.start` sends only when that needs no
waiting: codec settled, single-flight lock free, connection quiet (the stale-input check of
``exchange``), ``pc`` and timer unchanged; and counts the request as ``_send_request`` does.
When the codec takes the first chunk as the whole normal answer (``take_words``, the decision
of ``take_answer``, which ``_take_chunk`` tries first), the lane settles, releases and calls
back as ``_x_answered`` does. At the first sign of anything else (a send that fails, an answer
the codec does not take whole, a deadline, a lost connection, a transport that never takes
answers whole) it hands the exchange to the general steps (``RequestClient._x_adopt``) with
the state they would have kept, and they decide: the codec and the failure policy are never
bypassed, only the bookkeeping the plain case does not read. tests/test_callback_exchange.py
holds the lane to the awaited read on every case it has (split, extra, error codes, close
mid-answer, deadlines, datagrams, garbage).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from plcstack.codecs.e71 import ReadWords

if TYPE_CHECKING:
    from plcstack.clients.e71 import E71Client

__all__ = ["WordReadLane"]


class WordReadLane:
    """One checked word read (``request``, and ``what`` for messages) of one E71 client.

    ``read`` reuses ``request`` (checks and encoding done once); ``start_read`` runs
    :meth:`start`. A lane is also the transport's :class:`~plcstack.transports.base.Receiver`
    for the exchange it started. One exchange at a time: the client's lock guarantees it.
    """

    __slots__ = ("_client", "_handed", "request", "what")

    def __init__(self, client: E71Client, request: ReadWords, what: str) -> None:
        self._client = client
        self.request = request
        self.what = what
        #: whether the general steps run the exchange in flight (its ``done`` is the client's
        #: ``_x_done``, which ``abandon_exchange`` clears)
        self._handed = False

    def start(self, done: Callable[[Any], None]) -> bool:
        """Send this read now and return True, ``done`` later called once with the words or
        the error ``await client.read`` would raise (``done`` may run before this returns: a
        send that fails at once); or return False with nothing sent or changed."""
        client = self._client
        request = self.request
        if (
            not client._settled
            or request.pc != client.pc
            or request.timer != client.monitoring_timer
            or client.stale_check_needs_loop_pass
        ):
            return False
        transport = client.transport
        if not transport.quiet() or not client._lock.try_acquire():
            return False
        # what the general steps read while the exchange is in flight: that it is
        # (``abandon_exchange``), counted, and that the codec is no longer settled
        client._x_done = done
        self._handed = False
        client.stats.requests += 1
        client._settled = False
        try:
            transport.send_delivering(client.codec.send(request), self, client.timeout)
        except Exception as exc:
            self._hand_over(sent=False)
            client._x_failed(exc)
            return True
        if not client.quick_answers:  # no answer is taken whole here (UDP, ASCII)
            self._hand_over(sent=True)
        return True

    def chunk_received(self, data: bytes) -> None:
        """A chunk of the answer (:class:`Receiver`)."""
        client = self._client
        if self._handed:
            client.chunk_received(data)
            return
        try:
            words = client.codec.take_words(data)
        except Exception as exc:  # a bug in the codec: as the general step treats one
            self._hand_over(sent=True)
            client._x_failed(exc)
            return
        if words is None:  # not the whole normal answer alone: the general steps decide
            self._hand_over(sent=True)
            client.chunk_received(data)
            return
        # ``_take_chunk``'s quick step (``take_answer`` is ``take_words`` in an event), then
        # ``_x_answered`` with the E71 client's finish (``_finish_words``: the words as a list)
        client._answer_taken()
        done = client._x_end()
        done(list(words))

    def receive_failed(self, exc: Exception) -> None:
        """The deadline passed or the connection ended (:class:`Receiver`)."""
        self._hand_over(sent=True)
        self._client.receive_failed(exc)

    def _hand_over(self, *, sent: bool) -> None:
        """From here on the general callback steps run this exchange (at most once)."""
        if not self._handed:
            self._handed = True
            client = self._client
            client._x_adopt(client._finish, self.what, sent=sent)
