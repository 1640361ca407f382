"""Sparkplug B mode of the MQTT sink: the poller is an edge node, each PLC a device.

Topics (``G`` = ``[mqtt] group_id``, ``E`` = ``[mqtt] client_id`` as edge node id, ``D`` = PLC
name; ``/``, ``+``, ``#`` in names become ``_``)::

    spBv1.0/G/NBIRTH/E      on every connect and on a rebirth request: bdSeq, Node Control/Rebirth
    spBv1.0/G/NDEATH/E      the Last Will: bdSeq of the session it ends
    spBv1.0/G/DBIRTH/E/D    every tag of the PLC with its last value (is_null before the first)
    spBv1.0/G/DDATA/E/D     the tags of a scan (after report-by-exception)
    spBv1.0/G/DDEATH/E/D    when the PLC is unreachable (layout.Reachability: a scan failed for
                            want of the PLC, or every scan group's latest scan was all bad)
    spBv1.0/G/NCMD/E        subscribed: "Node Control/Rebirth" = true -> NBIRTH + all DBIRTHs
    spBv1.0/G/DCMD/E/D      subscribed: metric name = tag, value -> the poller's write_tag

Sequence numbers: ``seq`` is 0 in NBIRTH and counts 0..255 (wrapping) over every following
message of the session, assigned when the message is actually published. ``bdSeq`` counts
CONNECTs of the edge node (0..255, then 0 again) and is in the Will and the NBIRTH of the same
session. It is kept on disk (:mod:`plcstack.north.sparkplug_state`: ``[mqtt] state_path``, by
default next to ``buffer_path``) and saved before each CONNECT, so a restarted poller continues
the sequence instead of starting at 0 again. The Will (NDEATH) is not retained, as Sparkplug 3.0
requires: a retained death would tell every host that subscribes later that a live node is dead.

Metrics: one per tag, named as the tag; a tag with ``count > 1`` becomes ``tag/0``, ``tag/1``,
... (a folder in Ignition), which avoids the packed array encodings. The datatype comes from the
tag's declared type and scaling (:func:`declared_datatype`), never from a value, so the DBIRTH of
a cold start declares what every DDATA carries. Negative integers are two's complement in
``int_value``/``long_value`` as the specification says. A bad value is ``is_null`` with the
``Quality`` property 0 (BAD); a birth carries ``engUnit`` and ``documentation`` properties from the
tag's unit and description.

QoS: births, data and deaths at QoS 0, as Sparkplug 3.0 requires (the Will at QoS 1, as it
requires); ``[mqtt] sparkplug_qos = 1`` is a documented deviation (broker acknowledgements).

Store-and-forward: data queued while the broker was away is published after the new session's
NBIRTH and DBIRTHs, in order, each metric flagged ``is_historical``; births and deaths queued in
an old session are not replayed (the new session's births say the present state).

Writes: a DCMD is written through the sink's write path (the one value grammar; ``tag/3`` writes
one element of an array tag alone). Sparkplug has no reply message, so a refused
write is answered on the JSON mode's ``P/PLC/write/resp`` topic (``id`` = ``"dcmd:<metric>"``)
and counted; a confirmed one shows up in the next DDATA.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

from plcstack.north.buffer import Message
from plcstack.north.face import PlcUpdate, PollerView
from plcstack.north.layout import (
    Command,
    Publish,
    Reachability,
    Unanswerable,
    WriteRequest,
    topic_level,
)
from plcstack.north.mqtt import MqttSettings
from plcstack.north.sparkplug_pb import DATATYPES, Payload
from plcstack.north.sparkplug_state import BdSeqStore, default_state_path
from plcstack.poll.config import PollConfig, TagConfig
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.values import value_type

__all__ = ["NAMESPACE", "SparkplugLayout"]

log = logging.getLogger("plcstack.north.sparkplug")

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"

#: the tag's declared type -> Sparkplug datatype of each of its values (section "Data Types" of
#: the specification; the same widths as the OPC UA server's DataTypes)
_DECLARED = {
    "bool": "Boolean",
    "int8": "Int8",
    "uint8": "UInt8",
    "int16": "Int16",
    "uint16": "UInt16",
    "int32": "Int32",
    "uint32": "UInt32",
    "float32": "Float",
    "kf": "Int16",
    "kh": "UInt16",
    "km": "UInt16",
    "kz": "UInt16",
    "bcd16": "UInt16",
    "bcd32": "UInt32",
    "kt": "Double",  # seconds
    "kg": "Double",  # the KG range reaches below float32's normal range
    "ky": "String",  # two bytes as STEP 5 shows them: "12,255"
    "kc": "String",
}
#: a ``raw`` tag is one point: a bit, a byte (S5 byte areas) or a word
_RAW = {1: "Boolean", 8: "UInt8", 16: "UInt16"}
_INT32 = {1, 2, 3, 5, 6, 7}
_INT64 = {4, 8, 13}
#: Sparkplug's metric quality property (section "Quality Codes"): an Int32, 0 = BAD
QUALITY, QUALITY_BAD = "Quality", 0
#: the metric properties Ignition's MQTT Engine turns into the tag properties of these names
UNIT_PROPERTY, DESCRIPTION_PROPERTY = "engUnit", "documentation"


#: the error text of a metric in a birth before its tag's first scan
_NOT_YET = "no value yet"


def _tag_of(name: str, type_name: str, count: int) -> TagConfig:
    return TagConfig(name, "", value_type(type_name), count)


def declared_datatype(tag: TagConfig, point_bits: int = 16) -> int:
    """The Sparkplug datatype of one value of ``tag``, from its declared type and scaling alone
    (never from a value), so DBIRTH before the first scan says what every DDATA carries."""
    if tag.scale is not None:
        return DATATYPES["Double"]  # engineering units
    name = tag.type.name
    if name == "raw":
        return DATATYPES[_RAW.get(point_bits, "UInt16")]
    if tag.type.kind == "text":
        return DATATYPES["String"]
    return DATATYPES[_DECLARED.get(name, "Double")]


def _set_value(metric: Any, datatype: int, value: Any) -> None:
    """``value`` in the field ``datatype`` uses; is_null for None or a non-finite float."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        metric.is_null = True
    elif datatype == DATATYPES["Boolean"]:
        metric.boolean_value = bool(value)
    elif datatype in _INT32:
        metric.int_value = int(value) & 0xFFFFFFFF
    elif datatype in _INT64:
        metric.long_value = int(value) & 0xFFFFFFFFFFFFFFFF
    elif datatype == DATATYPES["Float"]:
        metric.float_value = float(value)
    elif datatype == DATATYPES["Double"]:
        metric.double_value = float(value)
    elif isinstance(value, tuple):  # KY: two bytes as read and written ("12,255")
        metric.string_value = ",".join(str(b) for b in value)
    else:
        metric.string_value = str(value)


def _property(metric: Any, key: str, datatype: int, value: Any) -> None:
    props = metric.properties
    props.keys.append(key)
    pv = props.values.add()
    pv.type = datatype
    if datatype == DATATYPES["String"]:
        pv.string_value = str(value)
    else:
        pv.int_value = int(value) & 0xFFFFFFFF


def metric_value(metric: Any) -> Any:
    """The Python value of a received metric (signed per its datatype), None if it has none."""
    kind = metric.WhichOneof("value")
    if kind is None or metric.is_null:
        return None
    value = getattr(metric, kind)
    width = {1: 8, 2: 16, 3: 32, 4: 64}.get(metric.datatype)
    if width is not None and isinstance(value, int) and not isinstance(value, bool):
        value &= (1 << width) - 1
        if value >= 1 << (width - 1):
            value -= 1 << width
    return value


class SparkplugLayout:
    """Turns samples into Sparkplug B messages and keeps the node's session state."""

    #: Sparkplug 3.0: the Will Message's retained flag MUST be false
    will_retain = False

    def __init__(
        self,
        group_id: str,
        edge_node: str,
        tags: Mapping[str, Sequence[TagConfig | tuple[str, str, int]]],
        *,
        prefix: str = "plcstack",
        qos: int = 0,
        state: BdSeqStore | None = None,
        point_bits: Mapping[tuple[str, str], int] | None = None,
    ) -> None:
        """``tags``: PLC -> its tags in configuration order (:class:`TagConfig`, or
        ``(name, type name, count)``); ``qos``: of births, data and deaths (Sparkplug 3.0 says
        0; 1 is ``[mqtt] sparkplug_qos = 1``); ``state``: where the bdSeq survives a restart
        (None: every start begins at 0); ``point_bits``: (PLC, tag) -> the width of a ``raw``
        tag's point (1, 8 or 16; the poller knows it), for its datatype."""
        self.group = topic_level(group_id)
        self.node = topic_level(edge_node)
        self.prefix = prefix
        self.qos = qos
        self.tags: dict[str, list[TagConfig]] = {
            plc: [t if isinstance(t, TagConfig) else _tag_of(*t) for t in specs]
            for plc, specs in tags.items()
        }
        self.state = state
        last = state.load() if state is not None else None
        # incremented by will() at the start of each session: the first CONNECT of a node that
        # never connected is 0, a restarted one continues after its last CONNECT
        self.bd_seq = -1 if last is None else last
        self.seq = 0
        self._last: dict[str, dict[str, Sample]] = {plc: {} for plc in tags}
        self.reachability = Reachability(
            {plc: {t.group for t in specs} for plc, specs in self.tags.items()}
        )
        self._dead: set[str] = set()  # PLCs whose last birth/death message was a DDEATH
        bits = point_bits or {}
        self._datatypes = {
            (plc, t.name): declared_datatype(t, bits.get((plc, t.name), 16))
            for plc, specs in self.tags.items()
            for t in specs
        }
        self._configs = {(plc, t.name): t for plc, specs in self.tags.items() for t in specs}
        self._plc_by_level = {topic_level(p): p for p in tags}
        self.rebirths = 0

    @classmethod
    def for_config(
        cls, settings: MqttSettings, poll_config: PollConfig, poller: PollerView | None = None
    ) -> SparkplugLayout:
        """The layout of ``[mqtt]`` ``settings`` for ``poll_config``'s PLCs; ``poller`` gives
        ``raw`` tags the width of their points."""
        tags = {plc.name: list(plc.tags) for plc in poll_config.plcs}
        point_bits: dict[tuple[str, str], int] = {}
        if poller is not None:
            for plc in tags:
                for name, (_, bits) in poller.tags(plc).items():
                    point_bits[(plc, name)] = bits
        path = settings.state_path or default_state_path(settings.buffer_path)
        if path is None:
            log.warning(
                "sparkplug: neither [mqtt] state_path nor buffer_path is set: bdSeq starts at 0 "
                "on every start, and a host may pair an old NDEATH with the new session"
            )
        state = BdSeqStore(path, settings.group_id, settings.client_id) if path else None
        return cls(
            settings.group_id,
            settings.client_id,
            tags,
            prefix=settings.prefix,
            qos=settings.sparkplug_qos,
            state=state,
            point_bits=point_bits,
        )

    # -- topics ---------------------------------------------------------------------------------
    def topic(self, kind: str, plc: str | None = None) -> str:
        base = f"{NAMESPACE}/{self.group}/{kind}/{self.node}"
        return base if plc is None else f"{base}/{topic_level(plc)}"

    # -- payloads -------------------------------------------------------------------------------
    def _next_seq(self) -> int:
        seq = self.seq
        self.seq = (seq + 1) % 256
        return seq

    def _bd_seq_payload(self, now: float, *, rebirth_metric: bool) -> Any:
        p = Payload()
        p.timestamp = int(now * 1000)
        m = p.metrics.add()
        m.name, m.datatype, m.long_value = "bdSeq", DATATYPES["Int64"], self.bd_seq
        m.timestamp = p.timestamp
        if rebirth_metric:
            r = p.metrics.add()
            r.name, r.datatype, r.boolean_value = REBIRTH, DATATYPES["Boolean"], False
            r.timestamp = p.timestamp
        return p

    def _add_metrics(self, p: Any, plc: str, samples: Sequence[Sample], *, birth: bool) -> None:
        """One metric per value: ``tag`` or ``tag/0``, ``tag/1``... with the tag's declared
        datatype; a bad value is is_null (with Quality BAD once the tag has been scanned); a
        birth carries the unit and description as properties."""
        for s in samples:
            config = self._configs.get((plc, s.tag))
            datatype = self._datatypes.get((plc, s.tag), DATATYPES["Double"])
            count = config.count if config is not None else 1
            ts = int(s.source_time * 1000)
            good = s.quality is Quality.GOOD
            value = s.value if good else None
            scanned = s.error != _NOT_YET
            items: list[Any]
            if count > 1 or isinstance(value, list):
                items = value if isinstance(value, list) else [None] * count
                names = [f"{s.tag}/{i}" for i in range(len(items))]
            else:
                items, names = [value], [s.tag]
            for name, item in zip(names, items, strict=True):
                m = p.metrics.add()
                m.name, m.timestamp, m.datatype = name, ts, datatype
                _set_value(m, datatype, item)
                if birth and config is not None:
                    unit = config.unit
                    description = config.description
                    if unit:
                        _property(m, UNIT_PROPERTY, DATATYPES["String"], unit)
                    if description:
                        _property(m, DESCRIPTION_PROPERTY, DATATYPES["String"], description)
                if not good and scanned:
                    _property(m, QUALITY, DATATYPES["Int32"], QUALITY_BAD)

    def probe(self, sample: Sample) -> None:
        """Raise if ``sample`` cannot be encoded as a metric; no state changes (the sink's
        supervisor finds the one sample a batch failed on with it)."""
        self._add_metrics(Payload(), sample.plc, [sample], birth=False)

    def _dbirth(self, plc: str, now: float) -> bytes:
        p = Payload()
        p.timestamp = int(now * 1000)
        last = self._last.get(plc, {})
        samples = []
        for tag in self.tags.get(plc, []):
            sample = last.get(tag.name)
            if sample is None:
                sample = Sample(plc, tag.name, None, Quality.BAD, now, now, _NOT_YET)
            samples.append(sample)
        self._add_metrics(p, plc, samples, birth=True)
        return bytes(p.SerializeToString())

    def _forget(self, plc: str) -> None:
        """Drop a device's metrics and their definitions (removed, or defined again)."""
        for table in (self._datatypes, self._configs):
            for key in [k for k in table if k[0] == plc]:
                del table[key]

    def update_plcs(self, update: PlcUpdate, now: float) -> list[Publish]:
        """A removed PLC dies (DDEATH, unless it is dead already) and is forgotten; an added
        one is born (DBIRTH, its metrics null until its first scan); a changed one whose
        metrics differ dies and is born again with the new ones (a host takes a device's
        metrics from its birth), each metric that stays keeping its last value. Every other
        device keeps its birth: no NBIRTH."""
        out: list[Publish] = []
        for plc in update.removed:
            if plc not in self.tags:
                continue
            if self.reachability.get(plc) is not False:
                out.append(self._death(plc, now))
            del self.tags[plc]
            self._last.pop(plc, None)
            self._dead.discard(plc)
            self._forget(plc)
        view = update.view
        configs = {p.name: p for p in view.config.plcs}
        reborn: list[str] = []
        for plc in (*update.added, *update.changed):
            tags = view.tags(plc)
            specs = list(configs[plc].tags)  # in the file's order, as at start
            types = {name: declared_datatype(tag, bits) for name, (tag, bits) in tags.items()}
            was = {t.name: t for t in self.tags.get(plc, ())}
            if was == {t.name: t for t in specs} and all(
                self._datatypes.get((plc, n)) == d for n, d in types.items()
            ):
                continue  # a new connection, the same metrics
            if plc in self.tags and self.reachability.get(plc) is not False:
                out.append(self._death(plc, now))
            self._forget(plc)
            self.tags[plc] = specs
            self._datatypes.update({(plc, name): d for name, d in types.items()})
            self._configs.update({(plc, t.name): t for t in specs})
            last = self._last.setdefault(plc, {})
            for name in [n for n in last if n not in tags]:
                del last[name]
            self._dead.discard(plc)
            reborn.append(plc)
            out.append(Publish(self.topic("DBIRTH", plc), self._dbirth(plc, now), self.qos, False))
        self._plc_by_level = {topic_level(p): p for p in self.tags}
        groups = {plc: {t.group for t in specs} for plc, specs in self.tags.items()}
        self.reachability.reconfigure(groups, reborn)
        return out

    def _death(self, plc: str, now: float) -> Publish:
        p = Payload()
        p.timestamp = int(now * 1000)
        return Publish(self.topic("DDEATH", plc), bytes(p.SerializeToString()), self.qos, False)

    # -- what the sink asks of a layout ---------------------------------------------------------
    def will(self, now: float) -> tuple[str, bytes]:
        """NDEATH with the new session's bdSeq (called once per connection attempt, before the
        CONNECT: the number is saved first, so even a crash right after it is counted)."""
        self.bd_seq = (self.bd_seq + 1) % 256
        if self.state is not None:
            self.state.save(self.bd_seq)
        p = self._bd_seq_payload(now, rebirth_metric=False)
        return self.topic("NDEATH"), bytes(p.SerializeToString())

    def births(self, now: float) -> list[Publish]:
        """NBIRTH (seq 0) and a DBIRTH for every PLC that is not known to be offline."""
        self.seq = 0
        out: list[Publish] = []
        p = self._bd_seq_payload(now, rebirth_metric=True)
        p.seq = self._next_seq()
        out.append(Publish(self.topic("NBIRTH"), bytes(p.SerializeToString()), self.qos, False))
        for plc in self.tags:
            if self.reachability.get(plc) is False:
                continue
            birth = Payload.FromString(self._dbirth(plc, now))
            birth.seq = self._next_seq()
            out.append(
                Publish(
                    self.topic("DBIRTH", plc), bytes(birth.SerializeToString()), self.qos, False
                )
            )
        return out

    def on_connect(self, now: float) -> list[Publish]:
        return self.births(now)

    def on_close(self, now: float) -> list[Publish]:
        """A graceful shutdown says NDEATH itself (the broker sends the Will only on a drop)."""
        p = self._bd_seq_payload(now, rebirth_metric=False)
        return [Publish(self.topic("NDEATH"), bytes(p.SerializeToString()), 1, False)]

    def subscriptions(self) -> list[str]:
        return [self.topic("NCMD"), self.topic("DCMD") + "/+"]

    def messages(self, scans: Sequence[Scan]) -> list[Publish]:
        """DDATA per PLC and scan; DDEATH/DBIRTH when a PLC becomes unreachable/reachable
        (:class:`~plcstack.north.layout.Reachability`: a group failing on its own only makes
        its metrics null with Quality BAD); ``seq`` is set when published."""
        out: list[Publish] = []
        for scan in scans:
            plc, samples = scan.plc, scan.samples
            if plc not in self.tags:
                continue  # no device of this node (yet, or any more): no DDATA without a birth
            last = self._last.setdefault(plc, {})
            for s in samples:
                last[s.tag] = s
            changed = self.reachability.update(scan)
            when = max(s.receive_time for s in samples)
            if changed is False:
                self._dead.add(plc)
                p = Payload()
                p.timestamp = int(when * 1000)
                out.append(
                    Publish(
                        self.topic("DDEATH", plc), bytes(p.SerializeToString()), self.qos, False
                    )
                )
                continue
            if self.reachability.get(plc) is False:
                continue  # dead: nothing until it is reachable again
            if changed is True and self._born_dead(plc):
                out.append(
                    Publish(self.topic("DBIRTH", plc), self._dbirth(plc, when), self.qos, False)
                )
                continue
            p = Payload()
            p.timestamp = int(min(s.source_time for s in samples) * 1000)
            self._add_metrics(p, plc, samples, birth=False)
            out.append(
                Publish(self.topic("DDATA", plc), bytes(p.SerializeToString()), self.qos, False)
            )
        return out

    def _born_dead(self, plc: str) -> bool:
        """Whether the PLC's last birth/death message was a DDEATH (so it needs a DBIRTH now);
        the births of a session already announced a PLC that was never seen unreachable."""
        dead = plc in self._dead
        self._dead.discard(plc)
        return dead

    def prepare(self, message: Message, replayed: bool) -> bytes | None:
        """At publish time: the session's next ``seq``; queued data from before the current
        session gets ``is_historical``; old births and deaths are dropped (None)."""
        kind = message.topic.split("/")[2] if message.topic.count("/") >= 3 else ""
        if replayed and kind in ("NBIRTH", "DBIRTH", "DDEATH", "NDEATH"):
            return None
        if not message.topic.startswith(NAMESPACE + "/"):
            return bytes(message.payload)  # a JSON write response
        p = Payload.FromString(message.payload)
        if kind == "NBIRTH":
            self.seq = 0
        p.seq = self._next_seq()
        if replayed:
            for m in p.metrics:
                m.is_historical = True
        return bytes(p.SerializeToString())

    # -- commands -------------------------------------------------------------------------------
    def commands(self, topic: str, payload: bytes) -> list[Command]:
        """NCMD ``Node Control/Rebirth`` = true: NBIRTH and every DBIRTH again, through the
        queue after what waits there (:meth:`prepare` numbers them from 0 at the NBIRTH when
        they are published); DCMD: a write per metric (metric name = tag, ``tag/3`` one
        element), answered only when refused (Sparkplug has no reply message: on the JSON
        mode's ``P/PLC/write/resp`` with ``id`` = ``"dcmd:<metric>"``)."""
        levels = topic.split("/")
        if len(levels) < 4 or levels[0] != NAMESPACE:
            return []
        try:
            p = Payload.FromString(payload)
        except Exception:  # not a Sparkplug payload: nothing to do, and nobody to answer
            return [Unanswerable(f"a {levels[2]} that is not a Sparkplug B payload")]
        if levels[2] == "NCMD":
            if not any(m.name == REBIRTH and metric_value(m) is True for m in p.metrics):
                return []
            self.rebirths += 1
            seq = self.seq
            births: list[Command] = list(self.births(time.time()))
            self.seq = seq
            return births
        if levels[2] == "DCMD" and len(levels) >= 5:
            level = levels[4]
            plc = self._plc_by_level.get(level)
            return [
                WriteRequest(plc, level, m.name, metric_value(m), f"dcmd:{m.name}", answer_ok=False)
                for m in p.metrics
            ]
        return []
