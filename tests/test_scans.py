"""Scans cross the north boundary as typed objects: the poller makes one ``Scan`` per completed
scan of a PLC's group, and every sink takes scans; nothing guesses the grouping back.

Before, the poller flattened each scan into samples and the north side cut the stream again by
a heuristic ("a tag repeats"); two groups of one PLC scanned at the same moment came out as one
message, and a sink had to rebuild the tag -> group map from the configuration.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Sequence
from typing import Any

import pytest

from plcstack.config import parse_config
from plcstack.north.config import NorthConfig
from plcstack.north.face import FaceBase
from plcstack.north.influx import InfluxFormat
from plcstack.north.layout import JsonLayout
from plcstack.north.mqtt import MqttSink, parse_mqtt
from plcstack.north.pipeline import North
from plcstack.north.rbe import ReportByException, ReportPolicy
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample, Scan, ScanQueue, ScanSink, flatten
from plcstack.poll.sinks import jsonl_text
from plcstack.poll.stats import PlcStats
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.scan_helpers import scan

T = 1_800_000_000.0


def good(plc: str, tag: str, value: Any, t: float = T) -> Sample:
    return Sample(plc, tag, value, Quality.GOOD, t, t + 0.001)


async def _take_scans(poller: Any, enough: int) -> list[Scan]:
    scans: list[Scan] = []
    async with asyncio.timeout(10):
        async for batch in poller.scans():
            assert batch and all(type(s) is Scan for s in batch)
            scans += batch
            if len(scans) >= enough:
                return scans
    raise AssertionError("the poller ended early")


# -- the poller makes scans -------------------------------------------------------------------
async def test_two_groups_of_one_plc_with_the_same_timing_are_two_scans() -> None:
    """Two groups on the same interval, read in the same loop pass (the callback scans of an
    E71): each scan is its own object, holding exactly its group's tags, with its group."""
    memory = MelsecMemory()
    memory.write_words("D", 0, [7, 8])
    sim = await e71.start(memory)
    try:
        tags = (
            TagConfig("a", "D0", group="left"),
            TagConfig("b", "D1", group="right"),
        )
        config = PollConfig((PlcConfig("p", sim.url, tags),), {"left": 0.02, "right": 0.02})
        async with Poller(config) as poller:
            scans = await _take_scans(poller, 20)
    finally:
        await sim.aclose()
    assert {(s.plc, s.group, tuple(x.tag for x in s.samples)) for s in scans} == {
        ("p", "left", ("a",)),
        ("p", "right", ("b",)),
    }
    for s in scans:
        assert s.samples[0].quality is Quality.GOOD
        assert s.source_time == s.samples[0].source_time <= s.receive_time
        assert s.receive_time == s.samples[0].receive_time


PLANT = """
[groups]
fast = 0.01
slow = 0.01

[[plc]]
name = "press"
url = "e71+tcp://127.0.0.1:1"

[plc.tags]
speed = { address = "D0", group = "fast" }
temp = { address = "D1", group = "slow" }
level = { address = "D2", group = "slow" }
count = "D3"
far = { address = "D500", group = "slow" }
"""


async def test_a_scans_group_is_what_the_config_says() -> None:
    """Every scan holds the tags the configuration puts in its group, whatever the requests
    (the slow group is two requests: D1..D2 and D500)."""
    from tests.poll_fakes import FakeClient

    config = parse_config(PLANT).poll
    groups = {t.name: t.group for t in config.plcs[0].tags}
    poller = Poller(config, client_factory=lambda plc: FakeClient("fake://press"))
    async with poller:
        scans = await _take_scans(poller, 12)
    seen = {s.group: sorted(x.tag for x in s.samples) for s in scans}
    assert seen == {
        "fast": ["speed"],
        "slow": ["far", "level", "temp"],
        "default": ["count"],
    }
    for s in scans:
        assert all(groups[x.tag] == s.group and x.plc == s.plc == "press" for x in s.samples)
        # a scan of several requests: its times span them
        assert s.source_time == min(x.source_time for x in s.samples)
        assert s.receive_time == max(x.receive_time for x in s.samples)


async def test_the_sample_iteration_and_batches_flatten_the_scans() -> None:
    """``async for sample in poller`` and ``batches()`` (the public sample API) give the
    samples of the scans in order: a flattening of the one queue, not a second one."""
    queue = ScanQueue(100)
    scans = [scan(good("p", "a", 1), good("p", "b", 2)), scan(good("q", "c", 3), group="g")]
    queue.put(scans)
    assert len(queue) == 3
    closed = [False]
    first = await queue.next_sample(lambda: closed[0])
    assert first.tag == "a" and len(queue) == 2
    closed[0] = True
    rest = [await queue.next_sample(lambda: True) for _ in range(2)]
    assert [first, *rest] == flatten(scans)
    with pytest.raises(StopAsyncIteration):
        await queue.next_sample(lambda: True)


# -- the bounded queue ------------------------------------------------------------------------
def test_a_full_queue_drops_whole_scans_and_counts_their_samples_per_plc() -> None:
    queue = ScanQueue(5)
    stats = {"p": PlcStats(), "q": PlcStats()}
    for name, s in stats.items():
        queue.count_drops(name, s)
    two = [scan(good("p", "a", i), good("p", "b", i)) for i in range(3)]
    queue.put(two)  # 6 samples > 5: the oldest scan goes, whole
    assert queue.held == 4 and len(queue.items) == 2 and queue.items[0] is two[1]
    assert (queue.dropped, queue.dropped_scans, stats["p"].drops) == (2, 1, 2)
    three = scan(good("q", "x", 1), good("q", "y", 1), good("q", "z", 1))
    queue.put([three])  # 7 > 5: the oldest scan goes until it fits
    assert list(queue.items) == [two[2], three] and queue.held == 5
    assert (queue.dropped, queue.dropped_scans, stats["p"].drops, stats["q"].drops) == (4, 2, 4, 0)
    # a scan larger than the whole buffer is kept (the newest is never dropped), never cut
    six = scan(*(good("q", f"t{i}", i) for i in range(6)))
    queue.put([six])
    assert list(queue.items) == [six] and queue.held == 6
    assert (queue.dropped, queue.dropped_scans, stats["p"].drops, stats["q"].drops) == (9, 4, 6, 3)
    assert queue.drain() == [six] and queue.held == 0 and len(queue) == 0


async def test_the_pollers_full_buffer_drops_scans_never_parts_of_one() -> None:
    from tests.test_poll_engine import make, tag

    poller, _ = make({"p": [tag("a", "D0"), tag("b", "D100"), tag("c", "D200")]}, queue=4)
    async with poller:
        async with asyncio.timeout(10):
            while poller.dropped < 9:  # noqa: ASYNC110 - counters, polled with a bound
                await asyncio.sleep(0.005)
        await poller.aclose()
        kept = poller.drain()
    stats = poller.stats["p"]
    assert kept and all([x.tag for x in s.samples] == ["a", "b", "c"] for s in kept)
    assert stats.drops == poller.dropped == 3 * poller.queue.dropped_scans
    assert stats.samples == poller.dropped + 3 * len(kept)


# -- report-by-exception per scan -------------------------------------------------------------
def test_rbe_filters_each_scan_and_keeps_its_group_and_times() -> None:
    rbe = ReportByException(ReportPolicy())
    first = scan(good("p", "a", 1), good("p", "b", 2), group="g")
    assert rbe.filter([first])[0] is first  # all reported: passed on as it is, no copy
    assert rbe.filter([first]) == []  # nothing changed: no scan at all
    moved = scan(good("p", "a", 1, T + 1), good("p", "b", 3, T + 1), group="g")
    [passed] = rbe.filter([moved])
    assert passed.samples == (moved.samples[1],)
    assert (passed.plc, passed.group, passed.source_time, passed.receive_time) == (
        "p",
        "g",
        moved.source_time,
        moved.receive_time,
    )
    # a scan all of whose samples are reported is passed on as it is (no copy)
    both = scan(good("p", "a", 5, T + 2), good("p", "b", 6, T + 2), group="g")
    assert rbe.filter([both])[0] is both


def test_north_reports_each_scan_after_rbe_to_every_sink() -> None:
    class Recorder(FaceBase):
        def __init__(self, name: str) -> None:
            self.name = name
            self.got: list[list[Scan]] = []

        def submit(self, scans: Sequence[Scan]) -> None:
            self.got.append(list(scans))

    plc = PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("a", "D0"), TagConfig("b", "D1")))
    poller = Poller(PollConfig((plc,), {"default": 1}))  # never started
    sink, other = Recorder("recorder"), Recorder("other")
    north = North(poller, NorthConfig(report=ReportPolicy()), faces=[sink, other])
    one = scan(good("p", "a", 1), good("p", "b", 1), group="x")
    two = scan(good("p", "a", 1, T + 1), good("p", "b", 2, T + 1), group="y")
    north.deliver([one])
    north.deliver([two])
    assert sink.got == other.got
    assert [[(s.group, [x.tag for x in s.samples]) for s in b] for b in sink.got] == [
        [("x", ["a", "b"])],
        [("y", ["b"])],
    ]


# -- every sink takes scans -------------------------------------------------------------------
def test_every_face_implements_the_one_protocol() -> None:
    """Checked by mypy (these lists are typed) and here: each face's ``submit`` takes scans,
    and it has every method of :class:`Face` (start, aclose, probe, health, summary, ...)."""
    import inspect

    from plcstack.north.face import Face
    from plcstack.north.history import History
    from plcstack.north.metrics import MetricsServer
    from plcstack.north.modbus.server import ModbusServer
    from plcstack.north.opcua import OpcUaServer
    from plcstack.north.stdout import StdoutLines
    from plcstack.north.web.server import WebConsole
    from plcstack.north.web.state import ConsoleState

    faces: list[type[Face]] = [
        MqttSink, WebConsole, ModbusServer, OpcUaServer, MetricsServer, StdoutLines, History
    ]  # fmt: skip
    sinks: list[type[ScanSink]] = [*faces, ConsoleState]
    members = [name for name in dir(Face) if not name.startswith("_")]
    for sink in sinks:
        [param] = list(inspect.signature(sink.submit).parameters.values())[1:]
        assert param.name == "scans", sink
    for face in faces:
        assert all(callable(getattr(face, m, None)) or m == "name" for m in members), face


def _two_groups_same_times() -> list[Scan]:
    """Two scans of one PLC, different groups, same tags' timing."""
    return [
        scan(good("p", "a", 1), group="fast"),
        scan(good("p", "b", 2), group="slow"),
    ]


def test_the_mqtt_sinks_messages_are_one_per_scan() -> None:
    sink = MqttSink(parse_mqtt({"url": "mqtt://127.0.0.1:1", "client_id": "c"}))
    sink.submit(_two_groups_same_times())
    topics = [m.topic for m in sink.buffer.peek(10)]
    assert topics == ["plcstack/p/status", "plcstack/p/data/fast", "plcstack/p/data/slow"]
    payloads = [json.loads(m.payload) for m in sink.buffer.peek(10)[1:]]
    assert [(p["group"], p["values"]) for p in payloads] == [("fast", {"a": 1}), ("slow", {"b": 2})]


def test_the_json_layout_and_the_stdout_formats_take_scans() -> None:
    layout = JsonLayout("plcstack", "c")
    data = [t for t, *_ in layout.messages(_two_groups_same_times()) if "/data/" in t]
    assert data == ["plcstack/p/data/fast", "plcstack/p/data/slow"]
    plc = PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("a", "D0"), TagConfig("b", "D1")))
    lines = InfluxFormat([plc]).lines(_two_groups_same_times())
    assert [line.split(" ")[0] for line in lines] == [
        "plc,plc=p,group=fast",
        "plc,plc=p,group=slow",
    ]
    text = jsonl_text([plc])(_two_groups_same_times())
    assert [json.loads(line)["tag"] for line in text.splitlines()] == ["a", "b"]


def test_the_sparkplug_layout_sends_a_ddata_per_scan() -> None:
    pytest.importorskip("google.protobuf")
    from plcstack.north.sparkplug import SparkplugLayout
    from plcstack.north.sparkplug_pb import Payload

    plc = PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("a", "D0"), TagConfig("b", "D1")))
    settings = parse_mqtt(
        {"url": "mqtt://127.0.0.1:1", "mode": "sparkplug", "group_id": "g", "client_id": "n"}
    )
    layout = SparkplugLayout.for_config(settings, PollConfig((plc,), {"default": 1}))
    out = layout.messages(_two_groups_same_times())
    assert [t for t, *_ in out] == ["spBv1.0/g/DDATA/n/p", "spBv1.0/g/DDATA/n/p"]
    assert [[m.name for m in Payload.FromString(body).metrics] for _, body, *_ in out] == [
        ["a"],
        ["b"],
    ]


def test_the_web_console_takes_scans() -> None:
    from plcstack.north.web.state import ConsoleState

    plc = PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("a", "D0"), TagConfig("b", "D1")))
    state = ConsoleState([plc])
    state.submit(_two_groups_same_times())
    assert {k: s.value for k, s in state.latest.items()} == {("p", "a"): 1, ("p", "b"): 2}
