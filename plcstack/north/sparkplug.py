"""Sparkplug B mode of the MQTT sink: the poller is an edge node, each PLC a device.

Topics (``G`` = ``[mqtt] group_id``, ``E`` = ``[mqtt] client_id`` as edge node id, ``D`` = PLC
name; ``/``, ``+``, ``#`` in names become ``_``)::

    spBv1.0/G/NBIRTH/E      on every connect and on a rebirth request: bdSeq, Node Control/Rebirth
    spBv1.0/G/NDEATH/E      the Last Will: bdSeq of the session it ends
    spBv1.0/G/DBIRTH/E/D    every tag of the PLC with its last value (is_null before the first)
    spBv1.0/G/DDATA/E/D     the tags of a scan (after report-by-exception)
    spBv1.0/G/DDEATH/E/D    when a whole scan of the PLC came back bad (unreachable)
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
... (a folder in Ignition), which avoids the packed array encodings. Data types follow the tag
type where it names a width (int16 -> Int16, uint32 -> UInt32, float32 -> Float, bool ->
Boolean), else the value (int -> Int64, float -> Double, str -> String). Negative integers are
two's complement in ``int_value``/``long_value`` as the specification says. A bad sample is
``is_null`` (its error text stays in the poller's statistics and the JSON mode).

Store-and-forward: data queued while the broker was away is published after the new session's
NBIRTH and DBIRTHs, in order, each metric flagged ``is_historical``; births and deaths queued in
an old session are not replayed (the new session's births say the present state).

Writes: a DCMD is written through ``write_tag``. Sparkplug has no reply message, so a refused
write is answered on the JSON mode's ``P/PLC/write/resp`` topic (``id`` = ``"dcmd:<metric>"``)
and counted; a confirmed one shows up in the next DDATA.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Sequence
from typing import Any

from plcstack.north.layout import topic_level
from plcstack.north.sparkplug_pb import DATATYPES, Payload
from plcstack.north.sparkplug_state import BdSeqStore, default_state_path
from plcstack.poll.samples import Quality, Sample

__all__ = ["NAMESPACE", "SparkplugLayout"]

log = logging.getLogger("plcstack.north.sparkplug")

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"

_BY_TYPE = {
    "bool": "Boolean",
    "int8": "Int8",
    "uint8": "UInt8",
    "int16": "Int16",
    "uint16": "UInt16",
    "int32": "Int32",
    "uint32": "UInt32",
    "float32": "Float",
}
_INT32 = {1, 2, 3, 5, 6, 7}
_INT64 = {4, 8, 13}


def _datatype(type_name: str, value: Any) -> int:
    if isinstance(value, bool):
        return DATATYPES["Boolean"]
    if isinstance(value, int):
        named = _BY_TYPE.get(type_name)
        code = DATATYPES[named] if named is not None else DATATYPES["Int64"]
        return code if code in _INT32 or code in _INT64 else DATATYPES["Int64"]
    if isinstance(value, float):
        return DATATYPES["Float"] if type_name == "float32" else DATATYPES["Double"]
    if isinstance(value, str):
        return DATATYPES["String"]
    named = _BY_TYPE.get(type_name)
    return DATATYPES[named] if named is not None else DATATYPES["Int64"]


def _set_value(metric: Any, datatype: int, value: Any) -> None:
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
    else:
        metric.string_value = str(value)


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
        tags: dict[str, list[tuple[str, str, int]]],
        *,
        prefix: str = "plcstack",
        qos: int = 1,
        state: BdSeqStore | None = None,
    ) -> None:
        """``tags``: PLC -> [(tag, type name, count)] in configuration order; ``state``: where
        the bdSeq survives a restart (None: every start begins at 0)."""
        self.group = topic_level(group_id)
        self.node = topic_level(edge_node)
        self.prefix = prefix
        self.qos = qos
        self.tags = tags
        self.state = state
        last = state.load() if state is not None else None
        # incremented by will() at the start of each session: the first CONNECT of a node that
        # never connected is 0, a restarted one continues after its last CONNECT
        self.bd_seq = -1 if last is None else last
        self.seq = 0
        self._last: dict[str, dict[str, Sample]] = {plc: {} for plc in tags}
        self._online: dict[str, bool] = {}
        self._types = {
            (plc, name): type_name for plc, specs in tags.items() for name, type_name, _ in specs
        }
        self._plc_by_level = {topic_level(p): p for p in tags}
        self.rebirths = 0
        self.writes_refused = 0

    @classmethod
    def for_config(cls, settings: Any, poll_config: Any) -> SparkplugLayout:
        tags = {
            plc.name: [(t.name, t.type.name, t.count) for t in plc.tags] for plc in poll_config.plcs
        }
        path = getattr(settings, "state_path", None) or default_state_path(settings.buffer_path)
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
            qos=settings.qos,
            state=state,
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
        for s in samples:
            type_name = self._types.get((plc, s.tag), "raw")
            ts = int(s.source_time * 1000)
            value = s.value if s.quality is Quality.GOOD else None
            if isinstance(value, list):
                for i, item in enumerate(value):
                    m = p.metrics.add()
                    m.name, m.timestamp = f"{s.tag}/{i}", ts
                    m.datatype = _datatype(type_name, item)
                    _set_value(m, m.datatype, item)
                continue
            count = next((c for n, _, c in self.tags.get(plc, []) if n == s.tag), 1)
            if value is None and count > 1:
                for i in range(count):
                    m = p.metrics.add()
                    m.name, m.timestamp, m.is_null = f"{s.tag}/{i}", ts, True
                    m.datatype = _datatype(type_name, None)
                continue
            m = p.metrics.add()
            m.name, m.timestamp = s.tag, ts
            m.datatype = _datatype(type_name, value)
            _set_value(m, m.datatype, value)

    def probe(self, sample: Sample) -> None:
        """Raise if ``sample`` cannot be encoded as a metric; no state changes (the sink's
        supervisor finds the one sample a batch failed on with it)."""
        self._add_metrics(Payload(), sample.plc, [sample], birth=False)

    def _dbirth(self, plc: str, now: float) -> bytes:
        p = Payload()
        p.timestamp = int(now * 1000)
        last = self._last.get(plc, {})
        samples = []
        for name, _type_name, _count in self.tags.get(plc, []):
            sample = last.get(name)
            if sample is None:
                sample = Sample(plc, name, None, Quality.BAD, now, now, "no value yet")
            samples.append(sample)
        self._add_metrics(p, plc, samples, birth=True)
        return bytes(p.SerializeToString())

    # -- what the sink asks of a layout ---------------------------------------------------------
    def will(self) -> tuple[str, bytes]:
        """NDEATH with the new session's bdSeq (called once per connection attempt, before the
        CONNECT: the number is saved first, so even a crash right after it is counted)."""
        self.bd_seq = (self.bd_seq + 1) % 256
        if self.state is not None:
            self.state.save(self.bd_seq)
        p = self._bd_seq_payload(time.time(), rebirth_metric=False)
        return self.topic("NDEATH"), bytes(p.SerializeToString())

    def births(self, now: float) -> list[tuple[str, bytes, int, bool]]:
        """NBIRTH (seq 0) and a DBIRTH for every PLC that is not known to be offline."""
        self.seq = 0
        out: list[tuple[str, bytes, int, bool]] = []
        p = self._bd_seq_payload(now, rebirth_metric=True)
        p.seq = self._next_seq()
        out.append((self.topic("NBIRTH"), bytes(p.SerializeToString()), 1, False))
        for plc in self.tags:
            if self._online.get(plc) is False:
                continue
            birth = Payload.FromString(self._dbirth(plc, now))
            birth.seq = self._next_seq()
            out.append((self.topic("DBIRTH", plc), bytes(birth.SerializeToString()), 1, False))
        return out

    def on_connect(self, now: float) -> list[tuple[str, bytes, int, bool]]:
        return self.births(now)

    def on_close(self, now: float) -> list[tuple[str, bytes, int, bool]]:
        """A graceful shutdown says NDEATH itself (the broker sends the Will only on a drop)."""
        p = self._bd_seq_payload(now, rebirth_metric=False)
        return [(self.topic("NDEATH"), bytes(p.SerializeToString()), 1, False)]

    def subscriptions(self) -> list[str]:
        return [self.topic("NCMD"), self.topic("DCMD") + "/+"]

    def messages(
        self, batch: Sequence[tuple[str, str, list[Sample]]]
    ) -> list[tuple[str, bytes, int, bool]]:
        """DDATA per PLC and scan; DDEATH/DBIRTH when a PLC goes offline/online (seq later)."""
        out: list[tuple[str, bytes, int, bool]] = []
        for plc, _group, samples in batch:
            last = self._last.setdefault(plc, {})
            for s in samples:
                last[s.tag] = s
            online = any(s.quality is Quality.GOOD for s in samples)
            was = self._online.get(plc)
            self._online[plc] = online
            when = max(s.receive_time for s in samples)
            if not online:
                if was is not False:
                    p = Payload()
                    p.timestamp = int(when * 1000)
                    out.append((self.topic("DDEATH", plc), bytes(p.SerializeToString()), 1, False))
                continue
            if was is False:
                out.append((self.topic("DBIRTH", plc), self._dbirth(plc, when), 1, False))
                continue
            p = Payload()
            p.timestamp = int(min(s.source_time for s in samples) * 1000)
            self._add_metrics(p, plc, samples, birth=False)
            out.append((self.topic("DDATA", plc), bytes(p.SerializeToString()), self.qos, False))
        return out

    def prepare(self, message: Any, replayed: bool) -> bytes | None:
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
    def handle(self, sink: Any, topic: str, payload: bytes) -> bool:
        levels = topic.split("/")
        if len(levels) < 4 or levels[0] != NAMESPACE:
            return False
        try:
            p = Payload.FromString(payload)
        except Exception:  # not a Sparkplug payload: nothing to do, and nobody to answer
            sink.stats.writes_refused += 1
            return True
        if levels[2] == "NCMD":
            if any(m.name == REBIRTH and metric_value(m) is True for m in p.metrics):
                self.rebirths += 1
                seq = self.seq
                for t, body, qos, retain in self.births(time.time()):
                    # through the queue, after what is queued: prepare() numbers them again,
                    # from 0 at the NBIRTH, when they are published
                    sink._put(t, body, qos, retain)
                self.seq = seq
            return True
        if levels[2] == "DCMD" and len(levels) >= 5:
            plc = self._plc_by_level.get(levels[4], levels[4])
            for m in p.metrics:
                task = asyncio.create_task(self._write(sink, plc, m.name, metric_value(m)))
                sink._writes.add(task)
                task.add_done_callback(sink._writes.discard)
            return True
        return False

    async def _write(self, sink: Any, plc: str, tag: str, value: Any) -> None:
        result = await sink.write_and_classify(plc, tag, value)
        if result is None:
            sink.stats.writes_ok += 1
        else:
            self.writes_refused += 1
            sink._respond(topic_level(plc), f"dcmd:{tag}", *result)
