"""What the Modbus server answers: the register image of the poller's latest values, and writes.

Reads never reach a PLC. Every sample the poller delivers is encoded once into its tag's
registers (:class:`RegisterImage`); a read request is answered from them. The rules, each for the
whole request (Modbus has no partial answers):

1. Any address of the span that no tag maps: exception 0x02 (illegal data address). A read may
   cover several tags and parts of a multi-register tag (the low word of a float32), as long as
   every address in it is mapped; gaps are refused, never filled.
2. Any tag in the span without a good value: 0x0B (gateway target device failed to respond) when
   its PLC does not answer (timeout, refused or lost connection, a broken reply) or has not been
   polled yet; 0x04 (server device failure) when the PLC answered with an error code or its
   points are no valid value of the tag's type.
3. Otherwise the registers (or bits).

Writes (FC 5, 6, 15, 16) go to the PLC through the writer (the poller's single-flight
``write_tag``), one tag after another in address order, and are answered only when the PLC has
confirmed every one. Refusals before anything is sent: 0x02 when an address is unmapped, the tag
is not ``writable = true``, or the span does not cover whole tags (a write of one word of a
float32 or of one element of an array would be a read-modify-write racing the PLC); 0x03 when the
value does not fit the tag's type. Failures: 0x0B when the PLC cannot be reached or did not
answer in time (after a send the outcome is unknown: the PLC may have executed it, and the log
says so), 0x04 when it answered with an error. A write over several tags that fails part way has
written the tags before the failing one; the log names them.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field

from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    PlcError,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.north.modbus.config import MapEntry
from plcstack.north.modbus.frames import (
    DEVICE_FAILURE,
    EXCEPTION_NAMES,
    GATEWAY_NO_RESPONSE,
    GATEWAY_PATH_UNAVAILABLE,
    ILLEGAL_ADDRESS,
    ILLEGAL_VALUE,
    Request,
)
from plcstack.north.modbus.registers import EncodeError
from plcstack.poll.samples import Quality, Sample
from plcstack.values import WordOrder

__all__ = ["Refused", "RegisterImage", "Writer", "exception_for"]

log = logging.getLogger("plcstack.north.modbus")

#: how a write reaches a PLC: (plc, tag, value), returns when the PLC confirmed it
Writer = Callable[[str, str, object], Awaitable[None]]


class Refused(Exception):
    """A request answered with Modbus exception ``code``; ``reason`` is for the log."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


def exception_for(error_type: type[BaseException] | None) -> int:
    """The exception code of a tag whose latest sample failed with ``error_type``."""
    if error_type is None or issubclass(
        error_type, PlcTimeout | ConnectionLost | RemoteProtocolError
    ):
        return GATEWAY_NO_RESPONSE
    return DEVICE_FAILURE


@dataclass(slots=True)
class _Slot:
    """One mapped tag and its registers as of the latest sample (None: no good value)."""

    entry: MapEntry
    words: list[int] | None = None
    code: int = GATEWAY_NO_RESPONSE
    why: str = "not polled yet"


@dataclass
class RegisterImage:
    """The mapped tags' registers, kept current from samples, and the request handling."""

    entries: list[MapEntry]
    order: WordOrder = WordOrder.BIG
    #: requests by function code, exception answers by code (the metrics)
    requests: Counter[int] = field(default_factory=Counter)
    exceptions: Counter[int] = field(default_factory=Counter)
    writes_confirmed: int = 0

    def __post_init__(self) -> None:
        self._index: dict[str, dict[int, tuple[_Slot, int]]] = {}
        self._by_tag: dict[tuple[str, str], _Slot] = {}
        for entry in self.entries:
            slot = _Slot(entry)
            self._by_tag[(entry.plc, entry.tag.name)] = slot
            table = self._index.setdefault(entry.layout.table, {})
            for offset in range(entry.layout.size):
                table[entry.layout.start + offset] = (slot, offset)

    # -- samples in -----------------------------------------------------------------------------
    def update(self, samples: Iterable[Sample]) -> None:
        """Take the poller's samples (tags without a ``modbus`` key are ignored)."""
        by_tag = self._by_tag
        for sample in samples:
            slot = by_tag.get((sample.plc, sample.tag))
            if slot is None:
                continue
            if sample.quality is Quality.GOOD:
                try:
                    slot.words = slot.entry.layout.encode(sample.value, self.order)
                    continue
                except (EncodeError, TypeError, ValueError) as exc:
                    slot.code, slot.why = DEVICE_FAILURE, f"value {sample.value!r}: {exc}"
            else:
                slot.code = exception_for(sample.error_type)
                slot.why = sample.error or "bad sample"
            slot.words = None

    # -- requests ------------------------------------------------------------------------------
    def read(self, request: Request) -> list[int]:
        """The registers (bits as 0/1) of a read request; :class:`Refused` per the rules above."""
        hits = self._span(request)
        out: list[int] = []
        for slot, offset in hits:
            words = slot.words
            if words is None:
                entry = slot.entry
                raise Refused(slot.code, f"{entry.describe()} has no good value: {slot.why}")
            out.append(words[offset])
        return out

    def _span(self, request: Request) -> list[tuple[_Slot, int]]:
        table = self._index.get(request.table, {})
        hits: list[tuple[_Slot, int]] = []
        for address in range(request.address, request.address + request.count):
            hit = table.get(address)
            if hit is None:
                raise Refused(ILLEGAL_ADDRESS, f"{request.table}:{address} is not mapped")
            hits.append(hit)
        return hits

    def plan_write(self, request: Request) -> list[tuple[MapEntry, object]]:
        """The (tag, value) writes of a write request, checked before anything is sent."""
        hits = self._span(request)
        jobs: list[tuple[MapEntry, object]] = []
        index = 0
        while index < len(hits):
            slot, offset = hits[index]
            entry = slot.entry
            size = entry.layout.size
            if offset != 0 or index + size > len(hits):
                raise Refused(
                    ILLEGAL_ADDRESS,
                    f"a write must cover whole tags: {entry.describe()} is only partly written",
                )
            if not entry.tag.writable:
                raise Refused(ILLEGAL_ADDRESS, f"{entry.describe()} is read-only (not writable)")
            words = list(request.values[index : index + size])
            jobs.append((entry, entry.layout.decode(words, self.order)))
            index += size
        return jobs

    async def write(self, request: Request, writer: Writer) -> None:
        """Carry out a write request tag by tag; :class:`Refused` at the first failure."""
        jobs = self.plan_write(request)
        done: list[str] = []
        for entry, value in jobs:
            name = f"{entry.plc}.{entry.tag.name}"
            try:
                await writer(entry.plc, entry.tag.name, value)
            except Exception as exc:
                code = write_exception(exc)
                before = f"; written before it: {', '.join(done)}" if done else ""
                unknown = isinstance(exc, PlcTimeout | ConnectionLost) and not isinstance(
                    exc, ConnectFailed
                )
                outcome = " (outcome unknown: the PLC may have executed it)" if unknown else ""
                if not isinstance(exc, PlcError):
                    log.exception("Modbus write of %s = %r failed", name, value)
                raise Refused(
                    code, f"write of {name} = {value!r} failed{outcome}: {exc}{before}"
                ) from None
            log.info("Modbus write of %s = %r confirmed by the PLC", name, value)
            self.writes_confirmed += 1
            done.append(name)

    def wrong_unit(self, request: Request, unit: int) -> Refused:
        return Refused(
            GATEWAY_PATH_UNAVAILABLE, f"unit identifier {request.unit}; this server is {unit}"
        )


def write_exception(exc: BaseException) -> int:
    """The exception code of a failed write (see the module's rules)."""
    if isinstance(exc, AddressError):
        return ILLEGAL_VALUE
    if isinstance(exc, PlcTimeout | ConnectionLost | RemoteProtocolError):
        return GATEWAY_NO_RESPONSE
    return DEVICE_FAILURE


def describe_code(code: int) -> str:
    return f"0x{code:02X} ({EXCEPTION_NAMES.get(code, 'unknown')})"
