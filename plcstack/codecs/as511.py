"""Siemens S5 AS511 (programming port) as Sans-IO state machines (spec part B).

AS511 is not a request/response framing: the PG (client) and the AG (PLC) answer each other
byte by byte (STX, DLE ACK, accept frame, parameter frame, data frame, terminate frame; B.4). So
both roles are machines that take received bytes *and the current time*, queue bytes to send
(:meth:`data_to_send`) and expose the next ``deadline`` at which the driver must call
:meth:`timer`. Nothing here reads a clock, sleeps or does I/O.

* :class:`ClientConnection` (the manual's PG; alias ``PGConnection``) runs one transaction
  (:class:`Job`) at a time (B.9.1) and reports one event per job: :class:`Response`,
  :class:`Nak` or :class:`Timeout`. Bytes that break the protocol make
  :meth:`ClientConnection.next_event` raise :class:`RemoteProtocolError` once. After any abort
  the machine refuses to start the next job until the line was silent for ``backoff`` (500 ms;
  B5.1/B5.5); :attr:`ClientConnection.ready_at` says when. Unlike the stream protocols there is
  no ERROR state: the line itself resynchronises after the silence, as the manual prescribes.
* :class:`ServerConnection` (the manual's AG; alias ``AGConnection``) is the PLC side (B.9.2):
  it emits :class:`Request` and the owner answers with :meth:`ServerConnection.respond` or
  :meth:`ServerConnection.refuse` (DLE NAK). On a gap or a wrong byte it silently returns to
  idle, as a CPU does.

Split along its seams: :mod:`~plcstack.codecs.as511_frames` holds the control characters and
DLE transparency (B.3), :mod:`~plcstack.codecs.as511_jobs` the jobs of the functions this library
uses (18h, 1Ah, 04h, 03h, 1Bh, 1Eh, stop/start through 03h; B.7) and the parsing of their
answers. This module holds the two machines and re-exports those names.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass

from plcstack.codecs._common import NEED_DATA, Event, NeedData, slot_init
from plcstack.codecs.as511_frames import (
    ACCEPT_FRAME,
    ACK,
    DC2,
    DLE,
    DLE_ACK,
    DLE_NAK,
    EOT,
    ETX,
    NAK,
    STX,
    SYN,
    TERMINATE_BYTES,
    TERMINATE_FRAME,
    Unstuffer,
    stuff,
    unstuff,
)
from plcstack.codecs.as511_jobs import (
    FN_B_INFO,
    FN_BLOCK_LIST,
    FN_OPERATING_MODE,
    FN_READ,
    FN_SYSTEM_PARAMETERS,
    FN_WRITE,
    MAX_READ_BYTES,
    MAX_WRITE_BYTES,
    READ_PREFIX,
    BlockInfo,
    Job,
    SystemAddresses,
    b_info_job,
    block_list_job,
    header_matches,
    operating_mode_job,
    parse_b_info,
    parse_read,
    parse_system_parameters,
    read_job,
    run_job,
    stop_job,
    system_parameters_job,
    write_job,
)
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "ACCEPT_FRAME",
    "ACK",
    "DC2",
    "DEFAULT_BACKOFF",
    "DEFAULT_CHAR_TIMEOUT",
    "DLE",
    "DLE_ACK",
    "DLE_NAK",
    "EOT",
    "ETX",
    "FN_BLOCK_LIST",
    "FN_B_INFO",
    "FN_OPERATING_MODE",
    "FN_READ",
    "FN_SYSTEM_PARAMETERS",
    "FN_WRITE",
    "MAX_READ_BYTES",
    "MAX_WRITE_BYTES",
    "NAK",
    "READ_PREFIX",
    "STX",
    "SYN",
    "TERMINATE_BYTES",
    "TERMINATE_FRAME",
    "AGConnection",
    "AGEvent",
    "BlockInfo",
    "ClientConnection",
    "Delivery",
    "Done",
    "Idled",
    "Job",
    "Nak",
    "PGConnection",
    "PGEvent",
    "Request",
    "Response",
    "ServerConnection",
    "SystemAddresses",
    "Timeout",
    "Unstuffer",
    "b_info_job",
    "block_list_job",
    "header_matches",
    "operating_mode_job",
    "parse_b_info",
    "parse_read",
    "parse_system_parameters",
    "read_job",
    "run_job",
    "stop_job",
    "stuff",
    "system_parameters_job",
    "unstuff",
    "write_job",
]

DEFAULT_CHAR_TIMEOUT = 0.5  # [R] B5.7: 500 ms for every wait, first answer byte included
DEFAULT_BACKOFF = 0.5  # B5.1 / B5.5
#: bytes an answer may exceed the expected length by before the PG gives up on it
_SLACK = 16
#: cap for answers of unknown length (18h, 1Bh)
_UNKNOWN_LENGTH_CAP = 4096
#: every byte value as a one-byte ``bytes`` (the function code the PG sends after DLE ACK)
_BYTE = tuple(bytes([b]) for b in range(256))
_DLE_EOT = bytes([DLE, EOT])
_STX_BYTE = bytes([STX])


# -- PG (client) machine (B.9.1) --------------------------------------------------------------
@slot_init
@dataclass(frozen=True, slots=True)
class Response(Event):
    """The transaction completed; ``data`` is the unstuffed data frame (empty for writes)."""

    fn: int
    data: bytes


@slot_init
@dataclass(frozen=True, slots=True)
class Nak(Event):
    """The AG answered DLE NAK at ``step`` ("ready", "function" or "params"; B5.1/B5.2)."""

    fn: int
    step: str


@slot_init
@dataclass(frozen=True, slots=True)
class Timeout(Event):
    """The AG did not answer within the character timeout while the PG was in ``state``."""

    fn: int
    state: str


PGEvent = Response | Nak | Timeout


class PGState(enum.Enum):
    IDLE = "IDLE"
    W_ACK1 = "W_ACK1"  # after STX, expect DLE ACK
    W_STX1 = "W_STX1"  # after fn, expect STX
    W_ACCEPT = "W_ACCEPT"  # expect accept byte + DLE ETX
    W_ACK2 = "W_ACK2"  # after the parameter frame, expect DLE ACK
    W_STX2 = "W_STX2"  # expect STX of the data frame
    RX_DATA = "RX_DATA"  # data frame until DLE ETX
    W_STX3 = "W_STX3"  # expect STX of the terminate frame
    W_END = "W_END"  # terminate byte + DLE ETX


class Delivery(enum.Enum):
    """How far the parameter frame of the current (or last) job got: for a write (03h, whose
    parameters carry the data) what the PLC can have done with it. Kept after an abort, so the
    driver can say the truth about a failed write (B.4 steps 8-10)."""

    #: the parameter frame was not queued for sending: nothing can have been executed
    NOT_SENT = "the data had not been sent, nothing was written"
    #: queued, but no DLE ACK for it: the PLC may have executed it and the answer got lost
    SENT = "the write may or may not have been executed"
    #: the AG answered DLE ACK after the parameter frame: it accepted and executed the job
    ACKNOWLEDGED = "the PLC had acknowledged the data (DLE ACK), so the write was executed"


#: the members as module names: an attribute of an Enum class costs a Python-level
#: ``EnumType.__getattr__`` hook in 3.11 (~0.1 us each), and the machines test states per byte
_IDLE = PGState.IDLE
_W_ACK1 = PGState.W_ACK1
_W_STX1 = PGState.W_STX1
_W_ACCEPT = PGState.W_ACCEPT
_W_ACK2 = PGState.W_ACK2
_W_STX2 = PGState.W_STX2
_RX_DATA = PGState.RX_DATA
_W_STX3 = PGState.W_STX3
_W_END = PGState.W_END
_NOT_SENT, _SENT, _ACKNOWLEDGED = Delivery.NOT_SENT, Delivery.SENT, Delivery.ACKNOWLEDGED

#: [R] B5.2/D.B5: DLE NAK is accepted at step 2 (busy), 4 (unsupported function), 9 (refused)
_NAK_STEPS = {
    PGState.W_ACK1: "ready",
    PGState.W_STX1: "function",
    PGState.W_ACK2: "params",
}


class ClientConnection:
    """The PG (client) side of AS511, one transaction at a time (B.9.1).

    Drive it like this: ``submit(job, now)`` (only when ``now >= ready_at``), send
    ``data_to_send()``, then until ``next_event()`` is not ``NEED_DATA``: wait for bytes until
    ``deadline``; pass them to ``receive_data(data, now)`` (``now``: when they arrived) or,
    when the deadline passed in silence, call ``timer(now)``; send ``data_to_send()`` after
    each call (a driver that could not watch the line calls :meth:`held_up` first).

    ``tx_byte_time`` is the line time of one byte (11 / baud for 8E1); deadlines that follow our
    own sending are extended by the time our bytes need on the wire, so a 512-byte write at 9600
    baud is not mistaken for a dead AG. ``response_timeout`` is the wait for the AG to execute a
    request (DLE ACK after the parameters and the STX of the data frame; D.B6).
    """

    def __init__(
        self,
        *,
        char_timeout: float = DEFAULT_CHAR_TIMEOUT,
        response_timeout: float | None = None,
        backoff: float = DEFAULT_BACKOFF,
        tx_byte_time: float = 0.0,
    ) -> None:
        if char_timeout <= 0 or backoff < 0 or tx_byte_time < 0:
            raise LocalProtocolError("char_timeout must be positive, backoff/tx_byte_time >= 0")
        self.char_timeout = char_timeout
        self.response_timeout = char_timeout if response_timeout is None else response_timeout
        self.backoff = backoff
        self.tx_byte_time = tx_byte_time
        self.state = _IDLE
        self.job: Job | None = None
        #: the PG may start the next transaction at this time (after NAK/abort: line silence)
        self.ready_at = 0.0
        #: when the current state times out; ``None`` when idle
        self.deadline: float | None = None
        #: the wait of the current state (what :meth:`held_up` grants again)
        self._period = char_timeout
        #: how far the current or last job's parameter frame got (see :class:`Delivery`)
        self.delivery = _NOT_SENT
        self._out = bytearray()
        self._events: deque[PGEvent | RemoteProtocolError] = deque()
        self._dle = False
        self._got_byte = False  # accept/terminate byte seen in W_ACCEPT / W_END
        self._rx: Unstuffer | None = None
        self._payload = b""

    # -- driver API --------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        return self.state is not _IDLE

    def submit(self, job: Job, now: float) -> None:
        """Start ``job``: queues the STX. Misuse (busy, in back-off) is a LocalProtocolError."""
        if self.state is not _IDLE or self._events:
            raise LocalProtocolError("an AS511 transaction is already in progress")
        if now < self.ready_at:
            raise LocalProtocolError(
                f"the line must be silent until {self.ready_at:.3f} (back-off after an abort)"
            )
        self.job = job
        self.delivery = _NOT_SENT
        self._dle = False
        self._send(_STX_BYTE)
        self._enter(_W_ACK1, now, sent=1)

    def data_to_send(self) -> bytes:
        out = self._out
        if not out:
            return b""
        data = bytes(out)
        out.clear()
        return data

    def next_event(self) -> PGEvent | NeedData:
        """The result of the current job, or NEED_DATA; raises RemoteProtocolError once."""
        if not self._events:
            return NEED_DATA
        event = self._events.popleft()
        if isinstance(event, RemoteProtocolError):
            raise event
        return event

    def receive_data(self, data: bytes, now: float) -> None:
        if type(data) is not bytes:
            data = bytes(data)
        i, n = 0, len(data)
        while i < n:
            state = self.state
            deadline = self.deadline
            if deadline is not None and now > deadline:
                self._receive_byte(data[i], now)  # too late: the byte path times out
                i += 1
                continue
            if state is _RX_DATA:
                # The data frame, up to 512 stuffed bytes: de-stuffed a run at a time instead of
                # byte by byte (the same checks; every byte of one chunk shares ``now``).
                i = self._receive_run(data, i, now)
                continue
            if not self._dle:
                # ``data[i:]`` starts with the whole answer the AG normally gives in this state
                # (DLE ACK, STX, the accept frame, the terminate frame 12 10 03): recognised in
                # one step, and the same transition taken as when its last byte arrives alone.
                # Anything else (NAK, garbage, another terminate byte, an answer split across
                # chunks) goes byte by byte below.
                job = self.job
                assert job is not None
                if state is _W_ACK1 or state is _W_ACK2:
                    if data.startswith(DLE_ACK, i):
                        i += 2
                        self._acked(state, job, now)
                        continue
                elif state is _W_STX1 or state is _W_STX2 or state is _W_STX3:
                    if data[i] == STX:
                        i += 1
                        self._stx_seen(state, job, now)
                        continue
                elif self._got_byte:
                    pass
                elif state is _W_ACCEPT:
                    if data.startswith(ACCEPT_FRAME, i):
                        i += 3
                        self._accepted(job, now)
                        continue
                elif state is _W_END and data.startswith(TERMINATE_FRAME, i):
                    i += 3
                    self._terminated(job)
                    continue
            self._receive_byte(data[i], now)
            i += 1

    def _receive_run(self, data: bytes, start: int, now: float) -> int:
        """RX_DATA: feed ``data[start:]`` to the de-stuffer; returns where to go on."""
        rx = self._rx
        assert rx is not None
        self.deadline = now + self.char_timeout  # re-armed by every byte (B.9.1)
        try:
            end = rx.feed_from(data, start)
        except RemoteProtocolError as exc:
            self._fail(now, f"data frame: {exc.message}")
            # The rest of the chunk arrives in IDLE, where bytes only extend the back-off
            # (which ``_fail`` has just set from the same ``now``).
            return len(data)
        if end < 0:
            return len(data)
        self._payload = rx.payload()
        self._rx = None
        self._send(DLE_ACK)
        self._enter(_W_STX3, now, sent=2)
        return end

    def timer(self, now: float) -> None:
        """Call when ``deadline`` has passed: aborts the transaction with a Timeout event."""
        if self.deadline is None or now < self.deadline or self.state is _IDLE:
            return
        job = self.job
        assert job is not None
        state = self.state.value
        self._abort(now)
        self._events.append(Timeout(job.fn, state))

    def held_up(self, now: float) -> None:
        """The driver could not watch the line until ``now``, past ``deadline`` (its event loop
        was held up), and saw no silence: the current wait starts again at ``now``. Call it
        before ``receive_data`` with bytes that waited meanwhile, or instead of ``timer`` when
        the deadline's timer ran late: a stalled driver must not time out an answer that came.
        """
        if self.deadline is not None and now > self.deadline:
            self.deadline = now + self._period

    def reset(self, now: float) -> None:
        """The line was re-opened: forget any transaction; keep (and restart) the back-off."""
        if self.state is not _IDLE:
            self._abort(now)
        self._events.clear()
        self._out.clear()

    # -- internals ---------------------------------------------------------------------------
    def _send(self, data: bytes) -> None:
        self._out += data

    def _enter(self, state: PGState, now: float, *, sent: int = 0, slow: bool = False) -> None:
        self.state = state
        self._dle = False
        wait = self.response_timeout if slow else self.char_timeout
        self._period = wait
        self.deadline = now + wait + sent * self.tx_byte_time

    def _abort(self, now: float) -> None:
        self.state = _IDLE
        self.deadline = None
        self._rx = None
        self._dle = False
        # [R] B5.5: silence is measured from the later of the abort and the last received byte
        self.ready_at = max(self.ready_at, now + self.backoff)

    def _fail(self, now: float, message: str) -> None:
        job = self.job
        fn = f"function {job.fn:02X}h" if job is not None else "idle"
        self._abort(now)
        self._events.append(RemoteProtocolError(f"AS511 {fn}, {message}"))

    def _nak(self, now: float) -> None:
        job = self.job
        assert job is not None
        step = _NAK_STEPS[self.state]
        self._abort(now)
        self._events.append(Nak(job.fn, step))

    # -- the transitions of the dialogue, each written once: taken when the last byte of an
    # expected answer arrives, alone (``_receive_byte``) or with the whole answer in one chunk
    # (``receive_data``)
    def _acked(self, state: PGState, job: Job, now: float) -> None:
        """DLE ACK in W_ACK1 (send the function code) or W_ACK2 (the AG executes the job)."""
        if state is _W_ACK1:
            self._send(_BYTE[job.fn])
            self._enter(_W_STX1, now, sent=1)
        else:
            self.delivery = _ACKNOWLEDGED
            self._enter(_W_STX2 if job.has_response else _W_STX3, now, slow=True)

    def _stx_seen(self, state: PGState, job: Job, now: float) -> None:
        """STX in W_STX1 (accept frame follows), W_STX2 (data frame) or W_STX3 (terminate)."""
        self._send(DLE_ACK)
        if state is _W_STX2:
            limit = job.response_length
            self._rx = Unstuffer(ETX, _UNKNOWN_LENGTH_CAP if limit is None else limit + _SLACK)
            self._enter(_RX_DATA, now, sent=2)
        else:
            self._got_byte = False
            self._enter(_W_ACCEPT if state is _W_STX1 else _W_END, now, sent=2)

    def _accepted(self, job: Job, now: float) -> None:
        """The accept frame is complete: acknowledge it and send the parameter frame."""
        params = job.params
        self._send(DLE_ACK)
        self._send(stuff(params) + _DLE_EOT)
        self.delivery = _SENT
        self._got_byte = False
        self._enter(_W_ACK2, now, sent=4 + len(params) + params.count(DLE), slow=True)

    def _terminated(self, job: Job) -> None:
        """The terminate frame is complete: acknowledge it; the job's event is ready."""
        self._send(DLE_ACK)
        self.state = _IDLE
        self.deadline = None
        self._dle = self._got_byte = False
        self._events.append(Response(job.fn, self._payload if job.has_response else b""))
        self._payload = b""

    def _receive_byte(self, byte: int, now: float) -> None:
        state = self.state
        if state is _IDLE:
            # B5.5: during back-off every byte extends the silence we wait for; a stray byte
            # outside a transaction means the line is not quiet either [R].
            self.ready_at = max(self.ready_at, now + self.backoff)
            return
        if self.deadline is not None and now > self.deadline:
            self.timer(now)  # the byte came too late: the transaction is already dead
            self.ready_at = max(self.ready_at, now + self.backoff)
            return
        job = self.job
        assert job is not None
        self.deadline = now + self.char_timeout  # re-armed on every byte (B.9.1)
        if state in (_W_ACK1, _W_ACK2):
            if not self._dle:
                if byte == DLE:
                    self._dle = True
                else:
                    self._fail(now, f"expected DLE ACK in {state.value}, got {byte:02X}h")
                return
            if byte == NAK:
                self._nak(now)
            elif byte != ACK:
                self._fail(now, f"expected DLE ACK in {state.value}, got DLE {byte:02X}h")
            else:
                self._acked(state, job, now)
            return
        if state is _W_STX1:
            if self._dle:
                if byte == NAK:
                    self._nak(now)
                else:
                    self._fail(now, f"expected STX after the function code, got DLE {byte:02X}h")
            elif byte == DLE:
                self._dle = True
            elif byte == STX:
                self._stx_seen(state, job, now)
            else:
                self._fail(now, f"expected STX after the function code, got {byte:02X}h")
            return
        if state in (_W_ACCEPT, _W_END):
            self._receive_short_frame(byte, now, job)
            return
        if state in (_W_STX2, _W_STX3):
            if byte != STX:
                self._fail(now, f"expected STX in {state.value}, got {byte:02X}h")
            else:
                self._stx_seen(state, job, now)
            return
        # RX_DATA never gets here: receive_data hands the data frame to _receive_run, and a
        # byte that came too late was dealt with above.

    def _receive_short_frame(self, byte: int, now: float, job: Job) -> None:
        """Accept frame (``16 10 03``) or terminate frame (``12 10 03``; lenient per D.B4)."""
        accept = self.state is _W_ACCEPT
        what = "accept frame" if accept else "terminate frame"
        if self._dle:
            if byte != ETX:
                self._fail(now, f"{what}: DLE followed by {byte:02X}h, expected DLE ETX")
                return
            if accept and not self._got_byte:
                self._fail(now, "accept frame without the AG answer byte (16h)")
                return
            if accept:
                self._accepted(job, now)
            else:
                self._terminated(job)
            return
        if byte == DLE:
            self._dle = True
        elif self._got_byte or (not accept and byte not in TERMINATE_BYTES):
            self._fail(now, f"{what}: unexpected byte {byte:02X}h")
        else:
            self._got_byte = True


# -- AG (PLC) machine (B.9.2) ------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Request(Event):
    """The PG sent a complete parameter frame; answer with ``respond()`` or ``refuse()``."""

    fn: int
    params: bytes


@dataclass(frozen=True, slots=True)
class Done(Event):
    """The PG acknowledged the terminate frame: the transaction is complete."""

    fn: int


@dataclass(frozen=True, slots=True)
class Idled(Event):
    """The AG dropped a transaction (gap, unexpected byte, bad frame; B5.6) and is idle again."""

    reason: str


AGEvent = Request | Done | Idled


class AGState(enum.Enum):
    IDLE = "IDLE"
    W_FN = "W_FN"
    W_ACK_A = "W_ACK_A"  # STX sent, expect DLE ACK, then send accept frame
    W_ACK_B = "W_ACK_B"  # accept frame sent, expect DLE ACK
    RX_PARAMS = "RX_PARAMS"
    EXECUTE = "EXECUTE"  # Request emitted, waiting for respond()/refuse()
    W_ACK_C = "W_ACK_C"  # STX sent, expect DLE ACK, then send the data frame
    W_ACK_D = "W_ACK_D"  # data frame sent, expect DLE ACK, then send STX
    W_ACK_E = "W_ACK_E"  # STX sent, expect DLE ACK, then send the terminate frame
    W_ACK_F = "W_ACK_F"  # terminate frame sent, expect DLE ACK


#: module names for the members (see the PGState ones)
_AG_IDLE = AGState.IDLE
_AG_W_FN = AGState.W_FN
_AG_W_ACK_A = AGState.W_ACK_A
_AG_W_ACK_B = AGState.W_ACK_B
_AG_RX_PARAMS = AGState.RX_PARAMS
_AG_EXECUTE = AGState.EXECUTE
_AG_W_ACK_C = AGState.W_ACK_C
_AG_W_ACK_D = AGState.W_ACK_D
_AG_W_ACK_E = AGState.W_ACK_E
_AG_W_ACK_F = AGState.W_ACK_F

#: functions the simulator answers (B.7: 18h, 1Ah, 04h, 03h, and the optional 1Bh, 1Eh)
DEFAULT_FUNCTIONS = frozenset(
    {FN_WRITE, FN_READ, FN_SYSTEM_PARAMETERS, FN_B_INFO, FN_BLOCK_LIST, FN_OPERATING_MODE}
)


class ServerConnection:
    """The AG (PLC) side of AS511 (B.9.2). Never raises on received bytes.

    ``busy`` makes it answer the next STX with DLE NAK (the "AG busy" case of B5.2).
    """

    def __init__(
        self,
        *,
        functions: frozenset[int] = DEFAULT_FUNCTIONS,
        char_timeout: float = DEFAULT_CHAR_TIMEOUT,
        max_params: int = 4096 + 2,
        tx_byte_time: float = 0.0,
    ) -> None:
        self.functions = functions
        self.char_timeout = char_timeout
        self.max_params = max_params
        self.tx_byte_time = tx_byte_time
        self.busy = False
        self.state = _AG_IDLE
        self.deadline: float | None = None
        self.fn = 0
        self._out = bytearray()
        self._events: deque[AGEvent] = deque()
        self._dle = False
        self._rx: Unstuffer | None = None
        self._response: bytes | None = None

    def data_to_send(self) -> bytes:
        out = bytes(self._out)
        self._out.clear()
        return out

    def next_event(self) -> AGEvent | NeedData:
        return self._events.popleft() if self._events else NEED_DATA

    def held_up(self, now: float) -> None:
        """The driver could not watch the line until ``now``, past ``deadline``, and saw no
        silence: the current wait starts again at ``now`` (as :meth:`ClientConnection.held_up`)."""
        if self.deadline is not None and now > self.deadline:
            self.deadline = now + self.char_timeout

    def timer(self, now: float) -> None:
        if self.deadline is not None and now >= self.deadline and self.state is not _AG_IDLE:
            self._idle(
                f"no answer from the PG within {self.char_timeout:g} s in {self.state.value}"
            )

    def respond(self, data: bytes | None, now: float) -> None:
        """Accept the pending Request: ``data`` is the data frame, ``None`` for "no data frame"."""
        if self.state is not _AG_EXECUTE:
            raise LocalProtocolError("respond() without a pending AS511 request")
        self._response = data
        self._send(DLE_ACK + bytes([STX]))
        self._enter(_AG_W_ACK_C if data is not None else _AG_W_ACK_E, now, 3)

    def refuse(self, now: float) -> None:
        """Refuse the pending Request: DLE NAK instead of DLE ACK (step 9; B5.1)."""
        if self.state is not _AG_EXECUTE:
            raise LocalProtocolError("refuse() without a pending AS511 request")
        self._send(DLE_NAK)
        self.state = _AG_IDLE
        self.deadline = None

    def receive_data(self, data: bytes, now: float) -> None:
        for byte in data:
            self._receive_byte(byte, now)

    # -- internals ---------------------------------------------------------------------------
    def _send(self, data: bytes) -> None:
        self._out += data

    def _enter(self, state: AGState, now: float, sent: int = 0) -> None:
        self.state = state
        self._dle = False
        self.deadline = now + self.char_timeout + sent * self.tx_byte_time

    def _withdraw_request(self) -> None:
        for i in range(len(self._events) - 1, -1, -1):
            if isinstance(self._events[i], Request):
                del self._events[i]
                return

    def _idle(self, reason: str) -> None:
        # [R] B5.6: on a gap or a wrong byte the AG silently returns to idle (no NAK)
        self.state = _AG_IDLE
        self.deadline = None
        self._dle = False
        self._rx = None
        self._events.append(Idled(reason))

    def _stx(self, now: float) -> None:
        if self.busy:
            self._send(DLE_NAK)
            self.state = _AG_IDLE
            self.deadline = None
            return
        self._send(DLE_ACK)
        self._enter(_AG_W_FN, now, 2)

    def _receive_byte(self, byte: int, now: float) -> None:
        state = self.state
        if state is _AG_IDLE:
            if byte == STX:
                self._stx(now)
            return  # anything else between transactions is ignored
        if state is _AG_EXECUTE:
            # The PG must wait for our answer; bytes now are a protocol breach (B5.6). A Request
            # the application has not taken yet is withdrawn with it: answering it later would
            # hit a state that belongs to another request (or none) - found by the robustness
            # fuzz, where the sim then raised LocalProtocolError out of respond().
            self._withdraw_request()
            self._idle(f"unexpected byte {byte:02X}h while executing a request")
            return
        if self.deadline is not None and now > self.deadline:
            self._idle(f"gap of more than {self.char_timeout:g} s in {state.value}")
            if byte == STX:
                self._stx(now)
            return
        self.deadline = now + self.char_timeout
        if state is _AG_W_FN:
            if self._dle:
                self._dle = False
                if byte != DLE:
                    self._idle(f"function code DLE {byte:02X}h")
                    return
            elif byte == DLE:
                self._dle = True  # D.B9: a function code 10h comes doubled
                return
            self.fn = byte
            if byte in self.functions:
                self._send(bytes([STX]))
                self._enter(_AG_W_ACK_A, now, 1)
            else:
                self._send(DLE_NAK)
                self.state = _AG_IDLE
                self.deadline = None
            return
        if state is _AG_RX_PARAMS:
            rx = self._rx
            assert rx is not None
            try:
                done = rx.feed(byte)
            except RemoteProtocolError as exc:
                self._idle(f"parameter frame: {exc.message}")
                return
            if done:
                self._rx = None
                self.state = _AG_EXECUTE
                self.deadline = None
                self._events.append(Request(self.fn, rx.payload()))
            return
        # W_ACK_A .. W_ACK_F: expect DLE ACK
        if not self._dle:
            if byte == DLE:
                self._dle = True
            elif byte == STX:
                self._idle(f"STX in {state.value}: the PG started over")  # B.9.2 [R]
                self._stx(now)
            else:
                self._idle(f"expected DLE ACK in {state.value}, got {byte:02X}h")
            return
        if byte != ACK:
            self._idle(f"expected DLE ACK in {state.value}, got DLE {byte:02X}h")
            return
        if state is _AG_W_ACK_A:
            self._send(ACCEPT_FRAME)
            self._enter(_AG_W_ACK_B, now, 3)
        elif state is _AG_W_ACK_B:
            self._rx = Unstuffer(EOT, self.max_params)
            self._enter(_AG_RX_PARAMS, now)
        elif state is _AG_W_ACK_C:
            data = stuff(self._response or b"") + bytes([DLE, ETX])
            self._send(data)
            self._enter(_AG_W_ACK_D, now, len(data))
        elif state is _AG_W_ACK_D:
            self._send(bytes([STX]))
            self._enter(_AG_W_ACK_E, now, 1)
        elif state is _AG_W_ACK_E:
            self._send(TERMINATE_FRAME)
            self._enter(_AG_W_ACK_F, now, 3)
        else:
            self.state = _AG_IDLE
            self.deadline = None
            self._response = None
            self._events.append(Done(self.fn))


#: the manual's names: PG (programming device, our client) and AG (the PLC)
PGConnection = ClientConnection
AGConnection = ServerConnection
