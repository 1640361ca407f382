"""The E71 face: MELSEC A-series 1E frames served in front of an E71, on its shared connection.

An E71 has eight connections; a plant that needs more partners, or partners in the other code
(binary / ASCII) or on the other transport (TCP / UDP), puts this face in front of it. Each
request a face client sends is decoded, executed on the PLC's one connection (the poller's,
through :class:`~plcstack.clients.share.SharedConnection`) and answered with what the PLC
answered, re-encoded in the face's code:

* device memory (00H-09H) and the read-only commands (0EH special module buffer, 15H CPU model,
  16H loopback, 17H/3BH extended file registers) go through as they are, with their own PC
  number and monitoring timer; an end code of the PLC comes back unchanged;
* monitoring: a registration (06H, 07H, 1AH) is the face client's own. It is sent on (the PLC
  checks it) and remembered; each monitor (08H, 09H, 1BH) sends it again and then the monitor,
  in one turn of the connection, so clients that register different points never see each
  other's. A monitor without its registration is 57H, as the E71 answers it;
* writes (02H-05H) only to what ``writable`` names
  (:class:`~plcstack.gateway.allow.DeviceAllowList`, nothing by default); anything else 55H
  ("write refused"), like an E71 whose CPU refuses;
* what a gateway must not pass on: program, parameter and comment commands, remote RUN/STOP,
  writes to special modules, extended file registers and the random access buffer: 55H;
  fixed-buffer telegrams and random access buffer reads, which are the E71 module's own: 50H.

When the PLC cannot be asked: a request that waited longer than its limit (the smaller of the
queue's ``max_wait`` and the request's own monitoring timer) is answered 60H and not sent, as
the E71 answers a request whose CPU exchange outlasts the timer; a dead or silent PLC is 60H
too; a full queue is 5BH with abnormal code 11H ("retry").
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import logging
from collections.abc import Callable
from typing import Any, Final

from plcstack.clients.e71 import E71Client
from plcstack.clients.share import QueueFull, SharedConnection, TurnRefused
from plcstack.codecs.e71 import (
    REQUEST_TYPES,
    Ack,
    BadRequest,
    BitsResponse,
    DeviceRef,
    ErrorResponse,
    ExtensionRequest,
    ExtensionResponse,
    MonitorBits,
    MonitorWords,
    OpaqueRequest,
    ReadBits,
    ReadWords,
    RegisterMonitorBits,
    RegisterMonitorWords,
    Request,
    Response,
    TestBits,
    TestWords,
    WordsResponse,
    WriteBits,
    WriteWords,
)
from plcstack.codecs.e71_commands import (
    Loopback,
    MonitorExt,
    ReadCpuModel,
    ReadExtDirect,
    ReadExtFile,
    ReadSpecial,
    RegisterMonitorExt,
)
from plcstack.errors import AddressError, ConnectFailed, PlcError
from plcstack.gateway.allow import DeviceAllowList
from plcstack.gateway.record import FaceWrite, WriteHook

__all__ = ["E71Executor", "Event", "Session", "command_of"]

log = logging.getLogger("plcstack.gateway.e71")

#: commands answered from the PLC as they are
_READS: Final = (
    ReadBits,
    ReadWords,
    ReadSpecial,
    ReadCpuModel,
    Loopback,
    ReadExtFile,
    ReadExtDirect,
)
_REGISTRATIONS: Final = (RegisterMonitorBits, RegisterMonitorWords, RegisterMonitorExt)
_MONITORS: Final = (MonitorBits, MonitorWords, MonitorExt)
_WRITES: Final = (WriteBits, WriteWords, TestBits, TestWords)
#: the registration each monitor needs
_NEEDS: Final[dict[type, type]] = {
    MonitorBits: RegisterMonitorBits,
    MonitorWords: RegisterMonitorWords,
    MonitorExt: RegisterMonitorExt,
}
#: extension commands that are the E71 module's own, not the CPU's (answered 50H)
_MODULE_OWN: Final = frozenset({0x60, 0x61, 0x62})

Event = Request | OpaqueRequest | ExtensionRequest | BadRequest
Answer = Response | ExtensionResponse


class Session:
    """What the E71 face keeps of one client: its monitor registration."""

    __slots__ = ("registration",)

    def __init__(self) -> None:
        self.registration: RegisterMonitorBits | RegisterMonitorWords | RegisterMonitorExt | None
        self.registration = None


def command_of(event: Event) -> int:
    """The command code of a decoded request (the subheader its answer echoes)."""
    if isinstance(event, BadRequest | OpaqueRequest):
        return event.command
    return event.COMMAND


class E71Executor:
    """Answers each decoded request from the PLC behind ``share`` (see the module docstring)."""

    def __init__(
        self,
        share: SharedConnection,
        *,
        writable: DeviceAllowList | None = None,
        on_write: WriteHook | None = None,
        read_previous: bool = False,
        face: str = "e71",
    ) -> None:
        client = share.client
        if not isinstance(client, E71Client):
            raise AddressError(
                f"{client.name}: an E71 face needs an E71 PLC (e71+tcp: or e71+udp:)"
            )
        self.share = share
        self.client: E71Client = client
        self.writable = writable if writable is not None else DeviceAllowList()
        self.on_write = on_write
        self.read_previous = read_previous
        self.face = face
        #: answers by outcome: ok (the PLC's answer, error codes included), denied, busy,
        #: expired, failed (the PLC did not answer)
        self.counts: collections.Counter[str] = collections.Counter()

    async def answer(self, event: Event, session: Session, peer: str | None) -> Answer:
        """The response to one request of the client at ``peer``."""
        if isinstance(event, BadRequest):
            return ErrorResponse(event.command, event.end_code)
        command = command_of(event)
        if isinstance(event, OpaqueRequest) or command in _MODULE_OWN:
            return ErrorResponse(command, 0x50)
        if isinstance(event, _WRITES):
            return await self._write(event, peer)
        if isinstance(event, _READS):
            return await self._ask(event, peer, [event])
        if isinstance(event, _REGISTRATIONS):
            answer = await self._ask(event, peer, [event])
            if isinstance(answer, Ack):
                session.registration = event
            return answer
        if isinstance(event, _MONITORS):
            registered = session.registration
            if registered is None or not isinstance(registered, _NEEDS[type(event)]):
                return ErrorResponse(command, 0x57)  # §7.3: monitor without its registration
            if isinstance(event, MonitorExt) and isinstance(registered, RegisterMonitorExt):
                event = dataclasses.replace(event, count=len(registered.points))
            return await self._ask(event, peer, [registered, event])
        self.counts["denied"] += 1
        return ErrorResponse(command, 0x55)  # programs, parameters, RUN/STOP, other writes

    # -- on the PLC's connection ----------------------------------------------------------------
    def _limit(self, event: Event) -> float:
        """How long a request may wait: the queue's limit, or its monitoring timer if shorter."""
        timer = event.timer if isinstance(event, REQUEST_TYPES) else 0
        wait = self.share.max_wait
        return min(wait, 0.25 * timer) if timer else wait

    async def _ask(self, event: Event, peer: str | None, requests: list[Any]) -> Answer:
        """``requests`` in one turn; the answer of the last (or the first error)."""
        client = self.client
        what = f"{self.face} face, {_name(event)} for {peer or 'a client'}"

        async def job() -> Answer:
            answer: Answer = ErrorResponse(command_of(event), 0x50)
            for request in requests:
                answer = await client.exchange(request, what, is_write=False)
                if isinstance(answer, ErrorResponse):
                    break
            return answer

        return await self._run(event, peer, job)

    async def _run(self, event: Event, peer: str | None, job: Callable[[], Any]) -> Answer:
        command = command_of(event)
        source: object = peer if peer is not None else asyncio.current_task()
        try:
            answer: Answer = await self.share.run(source, job, max_wait=self._limit(event))
        except QueueFull:
            self.counts["busy"] += 1
            return ErrorResponse(command, 0x5B, 0x11)
        except TurnRefused:
            self.counts["expired"] += 1
            return ErrorResponse(command, 0x60)
        except PlcError as exc:
            self.counts["failed"] += 1
            log.info("%s: %s", self.face, exc)
            return ErrorResponse(command, 0x60)
        self.counts["ok"] += 1
        return answer

    # -- writes ---------------------------------------------------------------------------------
    async def _write(
        self, event: WriteBits | WriteWords | TestBits | TestWords, peer: str | None
    ) -> Answer:
        command = event.COMMAND
        spans = _spans(event)
        where = ", ".join(str(ref) for ref, _ in spans)
        values = _values(event)
        if not all(self.writable.allows_ref(ref, n) for ref, n in spans):
            self.counts["denied"] += 1
            self._record(
                peer, where, values, None, "write_denied", False,
                f"write {where}: not allowed (writable: {self.writable})",
            )  # fmt: skip
            return ErrorResponse(command, 0x55)
        client = self.client
        what = f"{self.face} face, write {where} for {peer or 'a client'}"
        started = False

        async def job() -> Answer:
            nonlocal started
            started = True
            previous: list[int] | list[bool] | None = None
            writing = False
            try:
                if self.read_previous and isinstance(event, WriteBits | WriteWords):
                    before = await client.exchange(_read_back(event), what, is_write=False)
                    if isinstance(before, ErrorResponse):  # the write would meet the same
                        self._refused(peer, where, values, None, before, sent=False)
                        return ErrorResponse(command, before.end_code, before.abnormal_code)
                    if isinstance(before, BitsResponse | WordsResponse):
                        previous = list(before.values)
                writing = True
                answer: Answer = await client.exchange(event, what, is_write=True)
            except PlcError as exc:
                may = writing and not isinstance(exc, ConnectFailed)
                self._record(
                    peer, where, values, previous, "plc_timeout", may, f"write {where}: {exc}"
                )
                raise
            except BaseException:
                self._record(
                    peer, where, values, previous, "cancelled", writing,
                    f"write {where}: stopped while under way"
                    + ("; its outcome is unknown" if writing else "; not sent"),
                )  # fmt: skip
                raise
            if isinstance(answer, ErrorResponse):
                self._refused(peer, where, values, previous, answer, sent=True)
            else:
                self._record(
                    peer,
                    where,
                    values,
                    previous,
                    "ok",
                    True,
                    f"write {where}: confirmed by the PLC",
                )
            return answer

        try:
            answer = await self._run(event, peer, job)
        except asyncio.CancelledError:
            if not started:
                self._record(
                    peer, where, values, None, "cancelled", False,
                    f"write {where}: the client went away before its turn; not sent",
                )  # fmt: skip
            raise
        if not started and isinstance(answer, ErrorResponse):
            busy = answer.end_code == 0x5B
            self._record(
                peer, where, values, None, "busy" if busy else "plc_timeout", False,
                f"write {where}: "
                + ("too many requests wait for the PLC" if busy else "waited too long for the PLC")
                + "; not sent",
            )  # fmt: skip
        return answer

    def _refused(
        self,
        peer: str | None,
        where: str,
        values: list[int] | list[bool],
        previous: list[int] | list[bool] | None,
        answer: ErrorResponse,
        *,
        sent: bool,
    ) -> None:
        what = "the write" if sent else "reading the value before the write"
        self._record(
            peer, where, values, previous, "plc_refused", False,
            f"write {where}: the PLC answered {what} with end code {answer.code_text}: "
            f"{answer.meaning}" + ("" if sent else "; the write was not sent"),
        )  # fmt: skip

    def _record(
        self,
        peer: str | None,
        where: str,
        values: list[int] | list[bool],
        previous: list[int] | list[bool] | None,
        result: str,
        may_have_executed: bool,
        message: str,
    ) -> None:
        if self.on_write is not None:
            self.on_write(
                FaceWrite(
                    self.face, peer, where, values, previous, result, may_have_executed, message
                )
            )


def _name(event: Event) -> str:
    return f"{command_of(event):02X}H {type(event).__name__}"


def _spans(event: WriteBits | WriteWords | TestBits | TestWords) -> list[tuple[DeviceRef, int]]:
    """The points a write touches: ``(head, points)`` (a word of a bit device: 16 points)."""
    if isinstance(event, WriteBits):
        return [(event.ref, len(event.values))]
    if isinstance(event, WriteWords):
        per = 16 if event.ref.device.is_bit else 1
        return [(event.ref, per * len(event.values))]
    if isinstance(event, TestBits):
        return [(ref, 1) for ref, _ in event.points]
    return [(ref, 16 if ref.device.is_bit else 1) for ref, _ in event.points]


def _read_back(event: WriteBits | WriteWords) -> ReadBits | ReadWords:
    """The read of what a batch write is about to replace (the audit's ``previous``)."""
    if isinstance(event, WriteBits):
        return ReadBits(event.ref, len(event.values), pc=event.pc, timer=event.timer)
    return ReadWords(event.ref, len(event.values), pc=event.pc, timer=event.timer)


def _values(event: WriteBits | WriteWords | TestBits | TestWords) -> list[int] | list[bool]:
    if isinstance(event, WriteBits):
        return list(event.values)
    if isinstance(event, WriteWords):
        return list(event.values)
    if isinstance(event, TestBits):
        return [state for _, state in event.points]
    return [value for _, value in event.points]
