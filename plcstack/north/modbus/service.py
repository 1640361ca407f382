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

Writes (FC 5, 6, 15, 16) go through the run's one write path (:mod:`plcstack.north.writes`:
allow-list, value grammar, the poller's single-flight ``write_tag``, result codes, the audit with
source ``modbus``), one tag after another in address order, and are answered only when the PLC
has confirmed every one. Refusals before anything is sent: 0x02 when an address is unmapped, the
tag is not ``writable = true``, or the span does not cover whole tags (a write of one word of a
float32 or of one element of an array would be a read-modify-write racing the PLC). Then per
tag, from the write path's result: 0x03 when the value does not fit the tag's type, 0x06 when the
path is busy, 0x0B when the PLC cannot be reached or did not answer in time (after a send the
outcome is unknown: the PLC may have executed it, and the log says so), 0x04 when it answered
with an error. A write over several tags that fails part way has written the tags before the
failing one; the log names them.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from plcstack.errors import AddressError, ConnectionLost, PlcTimeout, RemoteProtocolError
from plcstack.north.modbus.config import MapEntry
from plcstack.north.modbus.frames import (
    DEVICE_BUSY,
    DEVICE_FAILURE,
    EXCEPTION_NAMES,
    GATEWAY_NO_RESPONSE,
    GATEWAY_PATH_UNAVAILABLE,
    ILLEGAL_ADDRESS,
    ILLEGAL_VALUE,
    Request,
)
from plcstack.north.modbus.registers import EncodeError
from plcstack.north.write_values import NOT_WRITABLE, UNKNOWN_TAG, WRONG_TYPE
from plcstack.north.writes import BAD_REQUEST, BUSY, UNKNOWN_PLC, WritePath, WriteResult
from plcstack.poll.samples import Quality, Scan
from plcstack.values import WordOrder

__all__ = ["Refused", "RegisterImage", "exception_for", "write_exception"]

log = logging.getLogger("plcstack.north.modbus")


class Refused(Exception):
    """A request answered with Modbus exception ``code``; ``reason`` is for the log
    (``logged``: the write path has logged it already)."""

    def __init__(self, code: int, reason: str, *, logged: bool = False) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason
        self.logged = logged


class _NotWritable(Refused):
    """A write refused before anything is sent, with what the audit records of it."""

    def __init__(self, entry: MapEntry, value: object, result: str, reason: str) -> None:
        super().__init__(ILLEGAL_ADDRESS, reason, logged=True)
        self.entry = entry
        self.value = value
        self.result = result


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
        self._map({})

    def remap(self, entries: list[MapEntry]) -> None:
        """The map of a reloaded configuration: a tag mapped as before keeps its registers
        and its latest value; a new or changed one reads as not polled yet; the registers of
        one no longer mapped are gone (exception 0x02)."""
        self.entries = entries
        self._map(self._by_tag)

    def _map(self, before: dict[tuple[str, str], _Slot]) -> None:
        self._index, self._by_tag = {}, {}
        for entry in self.entries:
            key = (entry.plc, entry.tag.name)
            slot = before.get(key)
            if slot is None or slot.entry != entry:
                slot = _Slot(entry)
            self._by_tag[key] = slot
            table = self._index.setdefault(entry.layout.table, {})
            for offset in range(entry.layout.size):
                table[entry.layout.start + offset] = (slot, offset)

    # -- samples in -----------------------------------------------------------------------------
    def update(self, scans: Iterable[Scan]) -> None:
        """Take the poller's scans (tags without a ``modbus`` key are ignored)."""
        by_tag = self._by_tag
        for sample in (s for scan in scans for s in scan.samples):
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

    def plan_write(
        self, request: Request, allowed: Callable[[str, str], WriteResult | None]
    ) -> list[tuple[MapEntry, object]]:
        """The (tag, value) writes of a write request, checked before anything is sent: every
        tag it covers whole, and admitted by the run's allow-list (``allowed``, the write
        path's), so a request is refused whole rather than half written."""
        hits = self._span(request)
        jobs: list[tuple[MapEntry, object]] = []
        index = 0
        while index < len(hits):
            slot, offset = hits[index]
            entry = slot.entry
            size = entry.layout.size
            words = list(request.values[index : index + size])
            if offset != 0 or index + size > len(hits):
                raise _NotWritable(
                    entry,
                    words,
                    BAD_REQUEST,
                    f"a write must cover whole tags: {entry.describe()} is only partly written",
                )
            value = entry.layout.decode(words, self.order)
            refusal = allowed(entry.plc, entry.tag.name)
            if refusal is not None:
                raise _NotWritable(
                    entry,
                    value,
                    refusal.code,
                    f"{entry.describe()} is read-only for north-side clients (set writable ="
                    " true in its configuration)"
                    if refusal.code == NOT_WRITABLE
                    else refusal.message,
                )
            jobs.append((entry, value))
            index += size
        return jobs

    async def write(self, request: Request, writes: WritePath, *, peer: str | None) -> None:
        """Carry out a write request tag by tag through the run's write path (allow-list, value
        grammar, the poller's write_tag, audit with source ``modbus`` and the client's address
        ``peer``); :class:`Refused` at the first refusal or failure."""
        try:
            jobs = self.plan_write(request, writes.allowed)
        except _NotWritable as refusal:
            entry = refusal.entry
            writes.refuse(
                "modbus",
                None,
                entry.plc,
                entry.tag.name,
                refusal.value,
                refusal.result,
                refusal.reason,
                peer=peer,
            )
            raise
        done: list[str] = []
        for entry, value in jobs:
            name = f"{entry.plc}.{entry.tag.name}"
            result = await writes.write("modbus", None, entry.plc, entry.tag.name, value, peer=peer)
            if result.ok:
                self.writes_confirmed += 1
                done.append(name)
                continue
            before = f"; written before it: {', '.join(done)}" if done else ""
            if result.may_have_executed:
                # the write path logged the failure; this says what it means for the client
                log.warning(
                    "Modbus write of %s = %r: outcome unknown, the PLC may have executed it%s",
                    name,
                    value,
                    before,
                )
            raise Refused(write_exception(result), f"{result.message}{before}", logged=True)

    def wrong_unit(self, request: Request, unit: int) -> Refused:
        return Refused(
            GATEWAY_PATH_UNAVAILABLE, f"unit identifier {request.unit}; this server is {unit}"
        )


#: write path result code -> exception code; "plc_error" is decided by the error's type
_RESULT_CODES = {
    NOT_WRITABLE: ILLEGAL_ADDRESS,
    UNKNOWN_TAG: ILLEGAL_ADDRESS,
    UNKNOWN_PLC: ILLEGAL_ADDRESS,
    WRONG_TYPE: ILLEGAL_VALUE,
    BAD_REQUEST: ILLEGAL_VALUE,
    BUSY: DEVICE_BUSY,
}


def write_exception(result: WriteResult) -> int:
    """The exception code of a refused or failed write (see the module's rules)."""
    code = _RESULT_CODES.get(result.code)
    if code is not None:
        return code
    if isinstance(result.error, AddressError):
        return ILLEGAL_VALUE
    if isinstance(result.error, PlcTimeout | ConnectionLost | RemoteProtocolError):
        return GATEWAY_NO_RESPONSE  # ConnectFailed included: the PLC cannot be reached
    return DEVICE_FAILURE


def describe_code(code: int) -> str:
    return f"0x{code:02X} ({EXCEPTION_NAMES.get(code, 'unknown')})"
