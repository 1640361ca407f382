"""MQTT topic and payload layout of the plain (JSON) mode, close to what EMQX Neuron users know.

``P`` is the configured prefix (default ``plcstack``), ``PLC`` a PLC name, ``GROUP`` a scan
group. Topic levels are the names as configured; ``/``, ``+``, ``#`` and NUL are replaced by
``_`` so a name can never add a level or a wildcard.

=====================================  =======  ======  ====================================
topic                                  retain   QoS     payload (JSON, UTF-8)
=====================================  =======  ======  ====================================
``P/PLC/data/GROUP``                   no       cfg     one scan group's scan: values and
                                                        per-tag errors (below)
``P/PLC/status``                       yes      1       ``{"status": "online"|"offline",
                                                        "timestamp": ms}``
``P/_poller/CLIENT_ID/status``         yes      1       the same for the poller itself;
                                                        ``offline`` is its Last Will
``P/PLC/write/req``                    no       -       ``{"id": ..., "tag": "t", "value": v}``
``P/PLC/write/resp``                   no       1       ``{"id": ..., "ok": true}`` or
                                                        ``{"id": ..., "ok": false, "error": code,
                                                        "message": text, "may_have_executed":
                                                        bool}``
=====================================  =======  ======  ====================================

A data message::

    {"plc": "press1", "group": "fast", "timestamp": 1795307490123,
     "values": {"strokes": 1200, "force": 12.5, "alarms": [false, true]},
     "errors": {"temp": "press1: read D200 x2: no answer within 2.0 s"}}

``timestamp`` is the scan's source time in milliseconds since the Unix epoch (the earliest
``source_time`` of its samples). A tag is in ``values`` (good) or in ``errors`` (bad), never both;
after report-by-exception a message holds only the tags that changed. A non-finite float is
reported in ``errors`` (``"non-finite value nan"``), since JSON has no NaN.

A PLC is ``offline`` when it cannot be reached: a scan failed for want of the PLC (timeout,
refused or dropped connection), or the latest scan of every scan group came back all bad. A group
that fails on its own (a value its type cannot decode) while another group reads fine makes only
its tags bad (in ``errors``); the PLC stays ``online``. A group that has not reported yet is
unknown, not bad: on a cold start no status is published until a group reads fine or every
group has reported. The status is published when it changes (:class:`Reachability`, the same
rule as Sparkplug's DDEATH/DBIRTH).

Write error codes: ``bad_request`` (not JSON, no ``tag`` or ``value``), ``unknown_plc``,
``unknown_tag``, ``not_writable`` (the tag lacks ``writable = true``: north-side clients may write
only tags marked so, as for OPC UA), ``wrong_type`` (value does not fit the tag's type or
count), ``plc_error`` (the PLC refused or did not answer; ``may_have_executed`` tells whether
the write could still have happened, e.g. after a timeout), ``busy`` (too many writes waiting).
``id`` is echoed as given (any JSON value; ``null`` if the request had none or was not JSON).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

from plcstack.errors import ConnectionLost, PlcTimeout
from plcstack.north.buffer import Message
from plcstack.north.face import PlcUpdate
from plcstack.output import float32_tags, shorten
from plcstack.poll.config import PlcConfig
from plcstack.poll.samples import Quality, Sample, Scan

__all__ = [
    "Command",
    "JsonLayout",
    "MqttLayout",
    "Publish",
    "Reachability",
    "Unanswerable",
    "WriteRequest",
    "data_payload",
    "data_topic",
    "poller_status_topic",
    "scan_groups",
    "status_payload",
    "status_topic",
    "topic_level",
    "write_request_topic",
    "write_response_payload",
    "write_response_topic",
]

_UNSAFE = re.compile(r"[/+#\x00]")


def topic_level(name: str) -> str:
    """A name as one topic level: no ``/`` (a new level), no wildcards, no NUL, never empty."""
    return _UNSAFE.sub("_", name) or "_"


def data_topic(prefix: str, plc: str, group: str) -> str:
    return f"{prefix}/{topic_level(plc)}/data/{topic_level(group)}"


def status_topic(prefix: str, plc: str) -> str:
    return f"{prefix}/{topic_level(plc)}/status"


def poller_status_topic(prefix: str, client_id: str) -> str:
    return f"{prefix}/_poller/{topic_level(client_id)}/status"


def write_request_topic(prefix: str, plc: str = "+") -> str:
    """The request topic of one PLC, or with ``+`` the subscription for all of them."""
    return f"{prefix}/{plc if plc == '+' else topic_level(plc)}/write/req"


def write_response_topic(prefix: str, plc: str) -> str:
    return f"{prefix}/{topic_level(plc)}/write/resp"


def _finite(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return True


def data_payload(
    plc: str,
    group: str,
    samples: Sequence[Sample],
    float32: Collection[tuple[str, str]] = (),
) -> bytes:
    """One data message from the samples of one PLC and scan group; tags in ``float32`` (PLC,
    tag) are printed at float32 precision (``-0.1``, not ``-0.10000000149011612``)."""
    values: dict[str, Any] = {}
    errors: dict[str, str] = {}
    for s in samples:
        if s.quality is Quality.GOOD and _finite(s.value):
            values[s.tag] = shorten(s.value) if (plc, s.tag) in float32 else s.value
        elif s.quality is Quality.GOOD:
            errors[s.tag] = f"non-finite value {s.value!r}"
        else:
            errors[s.tag] = s.error or "bad quality"
    record: dict[str, Any] = {
        "plc": plc,
        "group": group,
        "timestamp": round(min(s.source_time for s in samples) * 1000) if samples else 0,
        "values": values,
    }
    if errors:
        record["errors"] = errors
    return json.dumps(record, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode()


def status_payload(online: bool, timestamp: float) -> bytes:
    return json.dumps(
        {"status": "online" if online else "offline", "timestamp": round(timestamp * 1000)}
    ).encode()


def write_response_payload(
    request_id: Any,
    *,
    error: str | None = None,
    message: str | None = None,
    may_have_executed: bool = False,
) -> bytes:
    record: dict[str, Any] = {"id": request_id, "ok": error is None}
    if error is not None:
        record["error"] = error
        record["message"] = message or error
        record["may_have_executed"] = may_have_executed
    return json.dumps(record, ensure_ascii=False, allow_nan=False).encode()


class Publish(NamedTuple):
    """One message to publish: what a layout makes of scans, connects and commands."""

    topic: str
    payload: bytes
    qos: int
    retain: bool


@dataclass(frozen=True, slots=True)
class WriteRequest:
    """A write a client asked for over MQTT, as the layout understood it; the sink carries it
    out through the run's write path and answers on ``P/PLC/write/resp``.

    ``plc`` is None when the topic names no PLC of this run (``level``: the topic level it
    named, where the answer goes); ``error`` says why a request cannot be understood
    (``bad_request``); ``answer_ok``: whether a confirmed write is answered too (JSON) or only
    a refused one (Sparkplug has no reply message).
    """

    plc: str | None
    level: str
    tag: str | None
    value: object
    request_id: object = None
    error: str | None = None
    answer_ok: bool = True


@dataclass(frozen=True, slots=True)
class Unanswerable:
    """A command that cannot be understood and has nobody to answer (a DCMD that is not a
    Sparkplug payload): counted as a refused write, logged at DEBUG."""

    reason: str


#: what a layout makes of a message that came in on one of its subscriptions
Command = Publish | WriteRequest | Unanswerable


class MqttLayout(Protocol):
    """What the MQTT sink asks of a layout (:class:`JsonLayout`, or the Sparkplug B layout):
    the topics and payloads of scans, of a connect and of a clean stop, the Last Will, what to
    subscribe to, and what a received message asks for. The sink owns the connection, the
    queue and the writes; the layout owns the names, the encoding and its session state."""

    #: the Last Will's retained flag (Sparkplug 3.0: an NDEATH must not be retained)
    will_retain: bool

    def will(self, now: float) -> tuple[str, bytes]:
        """The Last Will of a connection opened at ``now`` (called once per attempt)."""
        ...

    def on_connect(self, now: float) -> list[Publish]:
        """Published first on every (re)connect, before the backlog."""
        ...

    def on_close(self, now: float) -> list[Publish]:
        """Published on a clean stop (the Will covers the other kind)."""
        ...

    def subscriptions(self) -> list[str]: ...

    def messages(self, scans: Sequence[Scan]) -> list[Publish]:
        """The messages of a batch of scans; all or nothing (raises before any state changes
        for a sample it cannot encode)."""
        ...

    def probe(self, sample: Sample) -> None:
        """Raise if ``sample`` cannot be encoded; no state changes."""
        ...

    def prepare(self, message: Message, replayed: bool) -> bytes | None:
        """The payload to publish for a queued message (``replayed``: it waited for this
        session), or None to skip it as obsolete."""
        ...

    def commands(self, topic: str, payload: bytes) -> list[Command]:
        """What a message received on a subscription asks for."""
        ...

    def update_plcs(self, update: PlcUpdate, now: float) -> list[Publish]:
        """Take the PLCs a reload added, removed and changed; the messages that say so to the
        broker's subscribers (a removed PLC's ``offline`` status or DDEATH, an added one's
        DBIRTH), queued after what waits."""
        ...


#: the failures that say the PLC itself cannot be reached (not a bad value in one group)
_UNREACHABLE = (PlcTimeout, ConnectionLost)


def scan_groups(plcs: Iterable[PlcConfig]) -> dict[str, frozenset[str]]:
    """PLC name -> the scan groups its tags are in: what :class:`Reachability` waits for."""
    return {plc.name: frozenset(t.group for t in plc.tags) for plc in plcs}


class Reachability:
    """Whether each PLC is reachable, by one rule for every north side (JSON status, Sparkplug
    DBIRTH/DDEATH).

    A PLC is unreachable when a scan failed for want of the PLC (a timeout, a refused or
    dropped connection) or when the latest scan of every one of its scan groups came back all
    bad. A group that keeps failing on its own (a BCD tag on a word holding 00AFH, an address the
    PLC refuses) while another group reads fine only makes its own values bad: the PLC stays
    reachable, so a host does not see it die and be born again every scan.

    A group that has not reported yet is unknown, not bad: until every group of the PLC
    (``groups``, from the configuration: :func:`scan_groups`) has reported, all-bad scans leave
    the state as it is (None before any decision), so a cold start whose failing group happens
    to report first does not declare a PLC dead that another group is about to show alive. A
    PLC missing from ``groups`` is judged by the groups seen so far.
    """

    def __init__(self, groups: Mapping[str, Collection[str]] | None = None) -> None:
        self._expected = {plc: frozenset(names) for plc, names in (groups or {}).items()}
        self._groups: dict[str, dict[str, bool]] = {}
        self._state: dict[str, bool] = {}
        #: PLCs a reload removed: the scans of their last requests, still on their way, decide
        #: nothing (a removed PLC said offline is never said online again by them)
        self._gone: set[str] = set()

    def update(self, scan: Scan) -> bool | None:
        """Record one scan; the PLC's new state if it changed (True reachable), else None."""
        plc, samples = scan.plc, scan.samples
        if self._gone and plc in self._gone:
            return None
        groups = self._groups.setdefault(plc, {})
        good = any(s.quality is Quality.GOOD for s in samples)
        groups[scan.group] = good
        if good:
            reachable = True
        elif any(s.error_type is not None and issubclass(s.error_type, _UNREACHABLE)
                 for s in samples):  # fmt: skip
            reachable = False
            for name in self._expected.get(plc, groups):  # each has to show the PLC back
                groups[name] = False
        elif any(groups.values()):
            reachable = True
        elif not self._expected.get(plc, frozenset()) <= groups.keys():
            return None  # a group not heard from yet may still read fine
        else:
            reachable = False
        if self._state.get(plc) is reachable:
            return None
        self._state[plc] = reachable
        return reachable

    def get(self, plc: str) -> bool | None:
        """The PLC's state: None before its first scan."""
        return self._state.get(plc)

    def reconfigure(
        self, groups: Mapping[str, Collection[str]], changed: Collection[str] = ()
    ) -> None:
        """The PLCs and scan groups of a reloaded configuration: a PLC no longer in ``groups``
        is forgotten (and its late scans ignored until a reload adds it again), a PLC in
        ``changed`` starts again from unknown (its groups may differ), every other keeps its
        state."""
        known = self._expected.keys() | self._state.keys() | self._groups.keys()
        self._gone = (self._gone | known) - groups.keys()
        self._expected = {plc: frozenset(names) for plc, names in groups.items()}
        for plc in [p for p in self._state.keys() | self._groups.keys()
                    if p not in groups or p in changed]:  # fmt: skip
            self._state.pop(plc, None)
            self._groups.pop(plc, None)


class JsonLayout:
    """The plain mode: turns scans into data and status messages, parses write requests."""

    will_retain = True

    def __init__(
        self,
        prefix: str,
        client_id: str,
        qos: int = 1,
        float32: Collection[tuple[str, str]] = (),
        groups: Mapping[str, Collection[str]] | None = None,
        *,
        plcs: Sequence[str] = (),
    ) -> None:
        """``float32``: (PLC, tag) of the float32 tags (:func:`plcstack.output.float32_tags`);
        ``groups``: each PLC's scan groups (:func:`scan_groups`), for :class:`Reachability`;
        ``plcs``: the PLCs whose write requests are taken and whose retained status says
        ``offline`` on a clean stop."""
        self.prefix = prefix
        self.client_id = client_id
        self.qos = qos
        self.float32 = float32
        self.reachability = Reachability(groups)
        #: each PLC's latest status message, published again on every (re)connect
        self._statuses: dict[str, bytes] = {}
        self.plc_by_level = {topic_level(p): p for p in plcs}

    # what the sink asks of a layout
    def will(self, now: float) -> tuple[str, bytes]:
        """The poller's ``offline``, stamped with the time its connection opened (the broker
        sends it later, when it loses the connection, and cannot stamp it): never 0."""
        return poller_status_topic(self.prefix, self.client_id), status_payload(False, now)

    def on_connect(self, now: float) -> list[Publish]:
        """Messages published first on every (re)connect, before the backlog: the poller's
        status, and every PLC's latest status again (retained): a broker that was restarted
        without its retained messages has none for a late subscriber, and the backlog holds
        only the changes made while it was away. Each keeps the time of its change; a status
        still in the backlog comes after and is the same or newer."""
        poller = poller_status_topic(self.prefix, self.client_id)
        return [Publish(poller, status_payload(True, now), 1, True)] + [
            Publish(status_topic(self.prefix, plc), payload, 1, True)
            for plc, payload in self._statuses.items()
        ]

    def on_close(self, now: float) -> list[Publish]:
        """A clean stop: every PLC's retained status ``offline`` first (nobody polls them any
        more: a retained ``online`` would stay true for ever), then the poller's."""
        prefix = self.prefix
        out = [
            Publish(status_topic(prefix, plc), status_payload(False, now), 1, True)
            for plc in self.plc_by_level.values()
        ]
        out.append(
            Publish(
                poller_status_topic(prefix, self.client_id), status_payload(False, now), 1, True
            )
        )
        return out

    def subscriptions(self) -> list[str]:
        return [write_request_topic(self.prefix)]

    def messages(self, scans: Sequence[Scan]) -> list[Publish]:
        """A data message per scan, after a status message when its PLC's state changed."""
        out: list[Publish] = []
        for scan in scans:
            plc, group, samples = scan.plc, scan.group, scan.samples
            online = self.reachability.update(scan)
            if online is not None:
                when = max(s.receive_time for s in samples)
                status = self._statuses[plc] = status_payload(online, when)
                out.append(Publish(status_topic(self.prefix, plc), status, 1, True))
            out.append(
                Publish(
                    data_topic(self.prefix, plc, group),
                    data_payload(plc, group, samples, self.float32),
                    self.qos,
                    False,
                )
            )
        return out

    def probe(self, sample: Sample) -> None:
        data_payload(sample.plc, "", [sample])

    def update_plcs(self, update: PlcUpdate, now: float) -> list[Publish]:
        """A removed PLC's retained status says ``offline`` (nobody polls it any more) and its
        write requests are refused as an unknown PLC's; an added one's are taken; a changed
        one's status is decided again from its next scans."""
        plcs = update.view.config.plcs
        out = []
        for plc in update.removed:
            self._statuses.pop(plc, None)
            status = status_payload(False, now)
            out.append(Publish(status_topic(self.prefix, plc), status, 1, True))
        self.plc_by_level = {topic_level(p.name): p.name for p in plcs}
        self.float32 = float32_tags(plcs)
        self.reachability.reconfigure(scan_groups(plcs), update.changed)
        return out

    def prepare(self, message: Message, replayed: bool) -> bytes | None:
        return message.payload

    def commands(self, topic: str, payload: bytes) -> list[Command]:
        """A write request on ``P/PLC/write/req``."""
        levels = topic.split("/")
        level = levels[-3] if len(levels) >= 3 else ""
        plc = self.plc_by_level.get(level)
        try:
            request = json.loads(payload)
        except (UnicodeDecodeError, ValueError) as exc:
            return [WriteRequest(plc, level, None, None, error=f"request is not JSON: {exc}")]
        if not isinstance(request, dict):
            return [WriteRequest(plc, level, None, None, error="request must be a JSON object")]
        request_id = request.get("id")
        tag = request.get("tag")
        if not isinstance(tag, str):
            error = 'request needs "tag" (a string)'
            return [WriteRequest(plc, level, None, None, request_id, error)]
        if "value" not in request:
            return [WriteRequest(plc, level, tag, None, request_id, 'request needs "value"')]
        return [WriteRequest(plc, level, tag, request["value"], request_id)]
