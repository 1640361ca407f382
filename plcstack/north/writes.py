"""The one write path of every north side: MQTT JSON, Sparkplug DCMD, OPC UA, web, Modbus, ...

```python
writes = WritePath(poller, audit=audit)          # one per run (North makes it)
result = await writes.write("mqtt", None, "press1", "setpoint", 1201, peer=None)
if not result.ok:
    answer(result.code, result.message, result.may_have_executed)
```

:meth:`WritePath.write` takes ``(source, user, plc, tag, value)`` and the client's ``peer``
(its network address, ``host:port`` as :func:`~plcstack.transports.peer.peer_address` spells
it; None where the north side cannot know it: MQTT and Sparkplug, whose broker hides the
publisher) and does, in this order:

1. the allow-list: the PLC and the tag must exist, and the tag must say ``writable = true``;
2. the value grammar every north side shares
   (:func:`~plcstack.north.write_values.parse_write_value`);
3. the poller's single-flight ``write_tag`` (never retried);
4. the result: a frozen :class:`WriteResult` with ``ok``, ``code``, ``message`` and
   ``may_have_executed``;
5. the audit line (:mod:`plcstack.north.audit`), written and flushed before it returns, so
   before the caller answers its client;
6. the log: a refused or failed write is one WARNING (the first of a run of equal refusals of
   one tag to one client: the same source, peer and user; the repeats at DEBUG), a confirmed
   one is INFO. A second client, or another login, refused the same tag is said again.

Result codes (the words MQTT write responses carry in ``error``; other sides map them onto their
own statuses): ``ok``, ``bad_request``, ``unknown_plc``, ``unknown_tag``, ``not_writable``,
``wrong_type``, ``busy``, ``plc_error``. ``may_have_executed`` is false only when the PLC
certainly did not execute the write: refused before sending, or answered with an error code.

A refusal the caller decides itself (a request it cannot parse, too many pending, a login that
may not write) goes through :meth:`WritePath.refuse`, and a write done on a path of its own (the
gateway's AS511 writes of addresses) through :meth:`WritePath.record`, so both are logged and
audited the same way.
"""

from __future__ import annotations

import difflib
import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Final

from plcstack.errors import PlcError
from plcstack.north.audit import Audit
from plcstack.north.face import PollerView
from plcstack.north.write_values import (
    NOT_WRITABLE,
    UNKNOWN_TAG,
    classify_write_error,
    parse_write_value,
    split_element,
    write_element,
)
from plcstack.poll.samples import Scan

__all__ = [
    "BAD_REQUEST",
    "BUSY",
    "OK",
    "PLC_ERROR",
    "UNKNOWN_PLC",
    "WritePath",
    "WriteResult",
]

log = logging.getLogger("plcstack.north.writes")

OK: Final = "ok"
BAD_REQUEST: Final = "bad_request"
BUSY: Final = "busy"
UNKNOWN_PLC: Final = "unknown_plc"
PLC_ERROR: Final = "plc_error"
#: a value that was never given (``previous`` unknown to the caller)
_UNSET: Final = object()


@dataclass(frozen=True, slots=True)
class WriteResult:
    """The outcome of one write attempt, as every north side answers it.

    ``code`` is ``"ok"`` or the result code; ``message`` says what happened in words (naming the
    PLC, the tag and the reason); ``error`` is the exception behind a failure, for a side that
    maps exception types onto its own status codes (OPC UA).
    """

    ok: bool
    code: str
    message: str
    may_have_executed: bool
    error: BaseException | None = None


class WritePath:
    """The write path of one run; see the module docstring.

    ``poller``: the run's poller (or a scale-out worker, which writes the PLCs it holds);
    None: nothing takes writes here (the gateway, which records its own), every write is
    refused ``not_writable``. ``audit``: where each attempt is recorded (None: no audit
    configured).
    """

    def __init__(self, poller: PollerView | None, *, audit: Audit | None = None) -> None:
        self.poller = poller
        self.audit = audit
        #: (plc, tag) -> last polled value, kept only while an audit needs ``previous``
        self.latest: dict[tuple[str, str], object] = {}
        self.ok = 0
        self.refused = 0
        #: (source, peer, user, plc, tag) -> the code of its latest refusal (repeats at DEBUG)
        self._last_code: dict[tuple[str, str | None, str | None, str, str], str] = {}

    def observe(self, scans: Iterable[Scan]) -> None:
        """Note the polled values of a batch of scans (the audit's ``previous``); a no-op
        without an audit."""
        if self.audit is None:
            return
        latest = self.latest
        for scan in scans:
            for s in scan.samples:
                latest[(s.plc, s.tag)] = s.value

    async def write(
        self,
        source: str,
        user: str | None,
        plc: str,
        tag: str,
        value: object,
        *,
        peer: str | None,
        previous: object = _UNSET,
    ) -> WriteResult:
        """One write attempt from a north-side client; never raises for the write's outcome.

        ``peer``: the client's address (``host:port``), None where the north side cannot
        know it; a required keyword, so no north side leaves it out by accident.
        ``previous``: the value the caller last showed its client (default: the last polled
        one this path saw).
        """
        if previous is _UNSET:
            previous = self.latest.get((plc, tag))
        result = await self._attempt(plc, tag, value)
        self._finish(source, user, peer, plc, tag, value, previous, result)
        return result

    def refuse(
        self,
        source: str,
        user: str | None,
        plc: str,
        tag: str,
        value: object,
        code: str,
        message: str,
        *,
        peer: str | None,
    ) -> WriteResult:
        """A refusal the caller decided before the write path (nothing was sent): logged and
        audited like any other, with the client's ``peer`` as in :meth:`write`."""
        result = WriteResult(False, code, message, False)
        self.record(source, user, plc, tag, value, result, peer=peer)
        return result

    def record(
        self,
        source: str,
        user: str | None,
        plc: str,
        tag: str,
        value: object,
        result: WriteResult,
        *,
        peer: str | None,
        previous: object = _UNSET,
    ) -> None:
        """Log and audit a write that a north side carried out on a path of its own (the
        gateway writes addresses over AS511, not tags through the poller)."""
        if previous is _UNSET:
            previous = self.latest.get((plc, tag))
        self._finish(source, user, peer, plc, tag, value, previous, result)

    def allowed(self, plc: str, tag: str) -> WriteResult | None:
        """The allow-list, the one of every north side: None if a write of ``tag`` (or of
        one element ``tag/N`` of an array tag) may be attempted, else the refusal (unknown
        PLC or tag, a tag without ``writable = true``, a poller that takes no writes).
        A face that must refuse a whole request before any of its writes is sent (a Modbus
        write spanning several tags) asks this first."""
        where = f"{plc}: write {tag}"
        poller = self.poller
        if poller is None:
            return WriteResult(
                False, NOT_WRITABLE, f"{where}: this poller takes no writes; not attempted", False
            )
        try:
            known = poller.tags(plc)
        except PlcError as exc:
            code, message, _ = classify_write_error(exc)
            return WriteResult(False, code, message, False, exc)
        config = known.get(tag)
        if config is None:
            element = split_element(tag)
            if element is None or element[0] not in known or known[element[0]][0].count < 2:
                close = difflib.get_close_matches(tag, list(known), n=1)
                meant = f" (did you mean {close[0]}?)" if close else ""
                return WriteResult(
                    False,
                    UNKNOWN_TAG,
                    f"{where}: no tag named {tag!r}{meant}; not attempted",
                    False,
                )
            config = known[element[0]]
        if not config[0].writable:
            return self._read_only(where)
        return None

    async def _attempt(self, plc: str, tag: str, value: object) -> WriteResult:
        refusal = self.allowed(plc, tag)
        if refusal is not None:
            return refusal
        poller = self.poller
        assert poller is not None  # allowed() refuses without one
        where = f"{plc}: write {tag}"
        try:
            known = poller.tags(plc)
            config = known.get(tag)
            if config is None:  # one value of an array tag (Sparkplug announces "alarms/3")
                element = split_element(tag)
                assert element is not None  # allowed() refuses any other unknown name
                base, bits = known[element[0]]
                await write_element(poller, plc, base, bits, element[1], value)
            else:
                parsed = parse_write_value(config[0], value, plc=plc)
                await poller.write_tag(plc, tag, parsed)
        except Exception as exc:  # every failure gets its answer, never silence
            code, message, may_have_executed = classify_write_error(exc)
            if not isinstance(exc, PlcError):
                log.error("%s: the write failed unexpectedly", where, exc_info=exc)
            return WriteResult(False, code, message, may_have_executed, exc)
        return WriteResult(True, OK, f"{where} = {value!r}: confirmed by the PLC", True)

    @staticmethod
    def _read_only(where: str) -> WriteResult:
        return WriteResult(
            False,
            NOT_WRITABLE,
            f"{where}: the tag is read-only for north-side clients (set writable = true in its"
            " configuration); not attempted",
            False,
        )

    def _finish(
        self,
        source: str,
        user: str | None,
        peer: str | None,
        plc: str,
        tag: str,
        value: object,
        previous: object,
        result: WriteResult,
    ) -> None:
        if self.audit is not None:
            self.audit.record(
                source=source,
                user=user,
                plc=plc,
                tag=tag,
                value=value,
                previous=previous,
                result=result.code,
                may_have_executed=result.may_have_executed,
                peer=peer,
                now=time.time(),
            )
        who = f"{source}" + (f" user {user}" if user else "")
        # the client's address last, after the message: the wording before it stays as it was
        client = f" (client {peer})" if peer else ""
        # who refused what: another client (peer) or login refused the same tag is a new line
        key = (source, peer, user, plc, tag)
        context = {"plc": plc, "tag": tag, "face": source}  # the fields of a JSON log line
        if result.ok:
            self.ok += 1
            self._last_code.pop(key, None)
            log.info("write from %s: %s%s", who, result.message, client, extra=context)
            return
        self.refused += 1
        # one WARNING per change: a client repeating the same refused write is not a log flood
        level = logging.DEBUG if self._last_code.get(key) == result.code else logging.WARNING
        if len(self._last_code) >= 4096:  # bounded, whatever names clients send
            self._last_code.clear()
        self._last_code[key] = result.code
        log.log(
            level,
            "write from %s refused (%s): %s%s",
            who,
            result.code,
            result.message,
            client,
            extra=context,
        )
