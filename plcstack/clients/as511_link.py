"""The AS511 link (PG side): one transaction of the byte-by-byte dialogue at a time.

AS511 talks byte by byte, so :class:`As511Link` drives the
:class:`~plcstack.codecs.as511.PGConnection` machine itself instead of
``RequestClient.exchange``; it keeps the base's single-flight lock, reconnect/backoff and
error binding. After a DLE NAK or any abort the next STX waits until the line was silent for
500 ms (B5.1, B5.5); bytes arriving meanwhile are discarded, so a late answer is never taken for
the next one. On a serial line that rule is the resynchronisation and the port stays open; over
TCP a timeout or malformed answer also closes the connection (a device server may have gone
away). The PG services (:mod:`plcstack.clients.as511_blocks`) and the client's API
(:mod:`plcstack.clients.as511`) are built on :meth:`As511Link.transact`.

The character timeout counts from when bytes arrived (the transport's data callback), and a
gap is only one the event loop saw: bytes that waited while the loop was held up are in time
(``PGConnection.held_up``).
"""

from __future__ import annotations

import asyncio

from plcstack.clients.base import (
    DEFAULT_CONNECT_TIMEOUT,
    DEFAULT_TIMEOUT,
    Client,
)
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import (
    DEFAULT_CHAR_TIMEOUT,
    Job,
    PGConnection,
    PGState,
    Response,
    Timeout,
)
from plcstack.diagnose import Failure, as511_hint
from plcstack.durations import check_seconds
from plcstack.errors import (
    ConnectionLost,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import HELD_UP, Transport
from plcstack.transports.serial import SerialTransport

__all__ = ["BITS_PER_BYTE", "As511Link"]

#: bits on the line per byte (8E1): a line's byte time without a serial port to ask
BITS_PER_BYTE = 11

_WAITING_FOR = {
    PGState.W_ACK1: "DLE ACK after STX (is the PLC connected, powered and on this port?)",
    PGState.W_STX1: "STX after the function code",
    PGState.W_ACCEPT: "the accept frame",
    PGState.W_ACK2: "DLE ACK after the parameters",
    PGState.W_STX2: "the data frame",
    PGState.RX_DATA: "the rest of the data frame",
    PGState.W_STX3: "the terminate frame",
    PGState.W_END: "the terminate frame",
}

_NAK_MEANING = {
    "ready": "the PLC is busy and refused to start a transaction (DLE NAK after STX)",
    "function": "the PLC does not support function {fn:02X}h (DLE NAK instead of STX)",
    "params": "the PLC refused the operation (DLE NAK after the parameters)",
}


class As511Link(Client):
    """One AS511 transaction at a time over a serial line or a serial device server."""

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        char_timeout: float = DEFAULT_CHAR_TIMEOUT,
        response_timeout: float | None = None,
        nak_backoff: float = 0.5,
        line_byte_time: float | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        connect_timeout: float = DEFAULT_CONNECT_TIMEOUT,
        backoff: Backoff | None = None,
    ) -> None:
        super().__init__(
            name, transport, timeout=timeout, connect_timeout=connect_timeout, backoff=backoff
        )
        char_timeout = check_seconds("char_timeout", char_timeout, plc=name)
        if response_timeout is not None:
            response_timeout = check_seconds("response_timeout", response_timeout, plc=name)
        if line_byte_time is None:
            line_byte_time = (
                transport.byte_time
                if isinstance(transport, SerialTransport)
                else BITS_PER_BYTE / 9600
            )
        self.line_byte_time = line_byte_time
        self.pg = PGConnection(
            char_timeout=char_timeout,
            response_timeout=response_timeout,
            backoff=nak_backoff,
            tx_byte_time=line_byte_time,
        )
        # A serial line resynchronises by the 500 ms silence rule; TCP may be half-open.
        self._drop_on_error = not isinstance(transport, SerialTransport)

    def connection_made(self) -> None:
        self.pg.reset(asyncio.get_running_loop().time())

    # -- one transaction --------------------------------------------------------------------
    async def transact(
        self, job: Job, what: str, *, is_write: bool = False, nak_meaning: str | None = None
    ) -> bytes:
        """Run one AS511 transaction and return its unstuffed data frame (b"" without one).

        Failures go through the clients' one failure policy (:meth:`Client.request_failed`);
        what a failed write had reached is the codec's :attr:`PGConnection.delivery`.
        """
        async with self._lock:
            await self._ensure_open(what)
            self.stats.requests += 1
            # every chunk received during this transaction, kept only for the failure hint
            chunks: list[bytes] = []
            pg = self.pg
            try:
                # The dialogue runs in this frame (no ``await self._run(...)``): every answer of
                # the AS511 dialogue resumes the whole chain of awaiting coroutines, so one
                # level less is paid 7 times per transaction.
                loop = asyncio.get_running_loop()
                out_bytes = 20 + 2 * len(job.params)
                in_bytes = 20 + 2 * (job.response_length or 64)
                cap = self.timeout + (out_bytes + in_bytes) * self.line_byte_time + pg.backoff
                # The whole transaction's bound, checked in the loop rather than by an
                # ``asyncio.timeout`` context (a timer and a context per transaction; AS511
                # runs 2-3 transactions per read): every wait is capped by it, and a peer that
                # keeps sending bytes meets the check after each chunk.
                give_up = loop.time() + cap
                transport = self.transport
                try:
                    # B5.1/B5.5: after an abort, wait for 500 ms of silence before the next STX.
                    while (wait := pg.ready_at - loop.time()) > 0:
                        try:
                            data = await transport.read(min(loop.time() + wait, give_up))
                        except TimeoutError:
                            if loop.time() >= give_up:
                                raise
                            continue
                        pg.receive_data(data, transport.arrived or loop.time())
                        if loop.time() >= give_up:
                            raise TimeoutError
                    pg.submit(job, max(loop.time(), pg.ready_at))
                    transport.write(pg.data_to_send())
                    while (event := pg.next_event()) is NEED_DATA:
                        deadline = pg.deadline
                        capped = deadline is None or deadline > give_up
                        try:
                            data = await transport.read(give_up if capped else deadline)
                        except TimeoutError:
                            if capped:
                                raise
                            # Silence is what the loop saw: a deadline whose timer ran late
                            # (the loop was held up and did not watch the line) is granted
                            # its wait again rather than failing an answer on its way.
                            now = loop.time()
                            if now - (deadline or 0.0) > HELD_UP:
                                pg.held_up(now)
                            else:
                                pg.timer(max(now, deadline or 0.0))
                        else:
                            chunks.append(data)
                            # when the bytes arrived, not when this coroutine resumed
                            now = transport.arrived or loop.time()
                            if now >= give_up:
                                raise TimeoutError from None
                            # read before the deadline's timer saw silence, so in time however
                            # late the loop saw them (a no-op before the deadline)
                            pg.held_up(now)
                            pg.receive_data(data, now)
                        out = pg.data_to_send()
                        if out:
                            transport.write(out)
                except TimeoutError:
                    state = pg.state
                    pg.reset(loop.time())
                    raise PlcTimeout(
                        f"no complete answer within {cap:.2f} s "
                        f"(AS511 transaction stuck in {state.value})"
                    ) from None
                except (ConnectionLost, RemoteProtocolError):
                    pg.reset(loop.time())
                    raise
            except asyncio.CancelledError:
                # The caller gave up mid-transaction: the PG must start over (B5.5 silence on a
                # line, a new connection on TCP), or every later request finds the transaction
                # "already in progress".
                pg.reset(asyncio.get_running_loop().time())
                if self._drop_on_error:
                    self.drop()
                raise
            except (PlcTimeout, ConnectionLost, RemoteProtocolError) as exc:
                failure: Failure = (
                    "timeout"
                    if isinstance(exc, PlcTimeout)
                    else "closed"
                    if isinstance(exc, ConnectionLost)
                    else "malformed"
                )
                # a serial line resynchronises from a timeout by silence (B5.5)
                drop = self._drop_on_error or failure != "timeout"
                raise self.request_failed(
                    exc,
                    failure,
                    b"".join(chunks),
                    what,
                    is_write=is_write,
                    sent=True,
                    drop=drop,
                    outcome=pg.delivery.value,
                ) from None
            if isinstance(event, Timeout):
                state = PGState(event.state)
                executing = state in (PGState.W_ACK2, PGState.W_STX2) or (
                    state is PGState.W_STX3 and not job.has_response
                )
                wait = pg.response_timeout if executing else pg.char_timeout
                error = PlcTimeout(
                    f"no complete answer within {wait:g} s (waiting for {_WAITING_FOR[state]})"
                )
                raise self.request_failed(
                    error,
                    "timeout",
                    b"".join(chunks),
                    what,
                    is_write=is_write,
                    sent=True,
                    drop=self._drop_on_error,
                    outcome=pg.delivery.value,
                )
            if self.unproven:
                self.answered()
        if isinstance(event, Response):
            return event.data
        self.stats.errors += 1
        meaning = _NAK_MEANING[event.step].format(fn=event.fn)
        if event.step == "params" and nak_meaning:
            meaning = nak_meaning
        raise PlcErrorResponse(0x15, meaning, plc=self.name, request=what, code_text="DLE NAK")

    def diagnose(self, failure: Failure, reply: bytes) -> str:
        serial = isinstance(self.transport, SerialTransport)
        return as511_hint(failure, reply, serial=serial, first=self.first_ever())
