"""Sparkplug B 3.0 as a host reads it: payloads decoded by the specification's field numbers and
datatype codes (a protobuf wire reader written here, not the product's schema), for every tag
type on a cold start, a group failing on its own, QoS, DCMD to an array element, properties."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import struct
from typing import Any

import aiomqtt
import pytest

from plcstack.clients.base import Client
from plcstack.errors import PlcTimeout, ValueDecodeError
from plcstack.north.config import NorthConfig
from plcstack.north.layout import JsonLayout, scan_groups
from plcstack.north.mqtt import MqttSettings, MqttSink, parse_mqtt
from plcstack.north.pipeline import North
from plcstack.north.sparkplug import SparkplugLayout
from plcstack.north.sparkplug_pb import Payload
from plcstack.north.writes import WritePath
from plcstack.poll.config import ConfigError, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.values import (
    BCD16,
    BCD32,
    BOOL,
    FLOAT32,
    INT8,
    INT16,
    INT32,
    KC,
    KF,
    KG,
    KH,
    KM,
    KT,
    KY,
    KZ,
    RAW,
    UINT8,
    UINT16,
    UINT32,
    string,
)  # fmt: skip
from plcstack.values.points import Scale
from tests.north_helpers import sample, subscriber
from tests.poll_fakes import FakeClient
from tests.scan_helpers import scan as as_scan
from tests.servers import Mosquitto

# -- the specification's wire format, read by hand ---------------------------------------------
# Payload: metrics = 2 (repeated Metric), seq = 3. Metric: name = 1, datatype = 4, is_null = 7,
# properties = 9, int_value = 10, long_value = 11, float_value = 12, double_value = 13,
# boolean_value = 14, string_value = 15. PropertySet: keys = 1, values = 2. PropertyValue:
# type = 1, int_value = 3, string_value = 8.
#: datatype codes of section "Data Types"
INT8_, INT16_, INT32_, INT64_, UINT8_, UINT16_, UINT32_ = 1, 2, 3, 4, 5, 6, 7
FLOAT_, DOUBLE_, BOOLEAN_, STRING_ = 9, 10, 11, 12


def _varint(data: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b = data[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, i


def fields(data: bytes) -> list[tuple[int, Any]]:
    """``(field number, value)`` in wire order: varints as int, 32/64-bit as bytes, strings and
    messages as bytes."""
    out: list[tuple[int, Any]] = []
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        number, wire = key >> 3, key & 7
        value: int | bytes
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 1:
            value, i = data[i : i + 8], i + 8
        elif wire == 5:
            value, i = data[i : i + 4], i + 4
        elif wire == 2:
            n, i = _varint(data, i)
            value, i = data[i : i + n], i + n
        else:
            raise AssertionError(f"wire type {wire}")
        out.append((number, value))
    return out


def wire_metrics(payload: bytes) -> dict[str, dict[str, Any]]:
    """name -> {datatype, is_null, value, properties} of each metric, by field number."""
    out: dict[str, dict[str, Any]] = {}
    for number, raw in fields(payload):
        if number != 2:
            continue
        m: dict[str, Any] = {"is_null": False, "value": None, "properties": {}}
        for f, v in fields(raw):
            if f == 1:
                m["name"] = v.decode()
            elif f == 4:
                m["datatype"] = v
            elif f == 7:
                m["is_null"] = bool(v)
            elif f == 9:
                keys = [k.decode() for n, k in fields(v) if n == 1]
                values = []
                for n, pv in fields(v):
                    if n == 2:
                        parts = dict(fields(pv))
                        values.append(parts.get(8, b"").decode() if 8 in parts else parts.get(3))
                m["properties"] = dict(zip(keys, values, strict=True))
            elif f in (10, 11, 14):
                m["value"] = v
            elif f == 12:
                m["value"] = struct.unpack("<f", v)[0]
            elif f == 13:
                m["value"] = struct.unpack("<d", v)[0]
            elif f == 15:
                m["value"] = v.decode()
        out[m["name"]] = m
    return out


# -- every tag type on a cold start -------------------------------------------------------------
#: (tag, its point width, a value as the poller delivers it, DBIRTH = DDATA datatype, on the wire)
TYPES: list[tuple[TagConfig, int, Any, int, Any]] = [
    (TagConfig("b", "M0", BOOL), 1, True, BOOLEAN_, 1),
    (TagConfig("i8", "D0", INT8), 16, -3, INT8_, 0xFFFFFFFD),
    (TagConfig("u8", "D1", UINT8), 16, 200, UINT8_, 200),
    (TagConfig("i16", "D2", INT16), 16, -5, INT16_, 0xFFFFFFFB),
    (TagConfig("u16", "D3", UINT16), 16, 65535, UINT16_, 65535),
    (TagConfig("i32", "D4", INT32), 16, -7, INT32_, 0xFFFFFFF9),
    (TagConfig("u32", "D6", UINT32), 16, 4000000000, UINT32_, 4000000000),
    (TagConfig("f32", "D8", FLOAT32), 16, -0.10000000149011612, FLOAT_, -0.10000000149011612),
    (TagConfig("level", "D10", INT16, scale=Scale(0, 100, 0, 10)), 16, 50.0, DOUBLE_, 50.0),
    (TagConfig("bcd", "D11", BCD16), 16, 1234, UINT16_, 1234),
    (TagConfig("bcd32", "D12", BCD32), 16, 12345678, UINT32_, 12345678),
    (TagConfig("kf", "D14", KF), 16, -1, INT16_, 0xFFFFFFFF),
    (TagConfig("kh", "D15", KH), 16, 0xABCD, UINT16_, 0xABCD),
    (TagConfig("km", "D16", KM), 16, 0x00FF, UINT16_, 0x00FF),
    (TagConfig("kz", "D17", KZ), 16, 999, UINT16_, 999),
    (TagConfig("kt", "D18", KT), 16, 1.5, DOUBLE_, 1.5),
    (TagConfig("kg", "D19", KG), 16, 1.5, DOUBLE_, 1.5),
    (TagConfig("ky", "D21", KY), 16, (12, 255), STRING_, "12,255"),
    (TagConfig("kc", "D22", KC), 16, "AB", STRING_, "AB"),
    (TagConfig("text", "D23", string(8)), 16, "Hello!", STRING_, "Hello!"),
    (TagConfig("word", "D27", RAW), 16, 17, UINT16_, 17),
    (TagConfig("bit", "M9", RAW), 1, True, BOOLEAN_, 1),
]


def cold_layout(**kwargs: Any) -> SparkplugLayout:
    tags = [t for t, *_ in TYPES] + [TagConfig("alarms", "M20", BOOL, count=3)]
    bits = {("p", t.name): b for t, b, *_ in TYPES} | {("p", "alarms"): 1}
    return SparkplugLayout("plant", "edge1", {"p": tags}, point_bits=bits, **kwargs)


def test_dbirth_before_the_first_scan_declares_each_tags_type_and_ddata_carries_it() -> None:
    layout = cold_layout()
    layout.will(0.0)
    (_, _nbirth, nqos, _), (topic, dbirth, qos, retain) = layout.births(1_800_000_000.0)
    assert topic == "spBv1.0/plant/DBIRTH/edge1/p" and (nqos, qos, retain) == (0, 0, False)
    born = wire_metrics(dbirth)
    for tag, _, _, datatype, _ in TYPES:
        assert born[tag.name]["datatype"] == datatype, tag
        assert born[tag.name]["is_null"] and born[tag.name]["value"] is None
        assert "Quality" not in born[tag.name]["properties"]  # not scanned yet: just null
    assert [born[f"alarms/{i}"]["datatype"] for i in range(3)] == [BOOLEAN_] * 3

    scan = [sample("p", t.name, value) for t, _, value, _, _ in TYPES]
    scan.append(sample("p", "alarms", [True, False, True]))
    [(topic, ddata, qos, _)] = layout.messages([as_scan(*scan, group="default")])
    assert topic == "spBv1.0/plant/DDATA/edge1/p" and qos == 0
    data = wire_metrics(ddata)
    for tag, _, _, datatype, wire in TYPES:
        assert data[tag.name]["datatype"] == datatype == born[tag.name]["datatype"], tag
        got = data[tag.name]["value"]
        if datatype == FLOAT_:
            assert struct.pack("<f", got) == struct.pack("<f", wire)
        else:
            assert got == wire, tag
    assert [data[f"alarms/{i}"]["value"] for i in range(3)] == [1, 0, 1]


def test_unit_and_description_are_metric_properties_of_the_birth() -> None:
    tag = TagConfig(
        "level", "D10", INT16, scale=Scale(0, 100, 0, 10), unit="m", description="tank 3 level"
    )
    layout = SparkplugLayout("plant", "edge1", {"p": [tag, TagConfig("plain", "D11", INT16)]})
    layout.will(0.0)
    born = wire_metrics(layout.births(1.0)[1][1])
    assert born["level"]["properties"] == {"engUnit": "m", "documentation": "tank 3 level"}
    assert born["plain"]["properties"] == {}
    # the PropertyValue type is String (12), by field number
    raw_metric = next(v for n, v in fields(layout.births(1.0)[1][1]) if n == 2)
    pset = next(v for n, v in fields(raw_metric) if n == 9)
    assert next(dict(fields(pv))[1] for n, pv in fields(pset) if n == 2) == STRING_


# -- a group that fails on its own, a PLC that is gone ---------------------------------------


def bad(plc: str, tag: str, error_type: type[Any]) -> Sample:
    return Sample(plc, tag, None, Quality.BAD, 1.0, 1.001, f"{plc}: read: failed", error_type)


def test_a_group_failing_on_its_own_makes_its_metrics_bad_not_the_device_dead() -> None:
    tags = [TagConfig("ok", "D0", UINT16), TagConfig("code", "D1", BCD16, group="slow")]
    layout = SparkplugLayout("plant", "edge1", {"p": tags})
    json_layout = JsonLayout("plcstack", "poller")
    kinds: list[str] = []
    statuses: list[bytes] = []
    for n in range(5):  # the BCD word holds 00AFH: that group fails every scan
        for group, scan in (
            ("default", [sample("p", "ok", n)]),
            ("slow", [bad("p", "code", ValueDecodeError)]),
        ):
            kinds += [t.split("/")[2] for t, *_ in layout.messages([as_scan(*scan, group=group)])]
            statuses += [
                body
                for t, body, *_ in json_layout.messages([as_scan(*scan, group=group)])
                if "status" in t
            ]
    assert set(kinds) == {"DDATA"}
    assert [json.loads(s)["status"] for s in statuses] == ["online"]
    last = layout.messages([as_scan(bad("p", "code", ValueDecodeError), group="slow")])[0][1]
    code = wire_metrics(last)["code"]
    assert code["is_null"] and code["properties"] == {"Quality": 0}  # Sparkplug's BAD
    assert code["datatype"] == UINT16_

    # the PLC stops answering: one DDEATH (and JSON offline), then a DBIRTH when it is back
    gone = [as_scan(bad("p", "ok", PlcTimeout))]
    assert [t.split("/")[2] for t, *_ in layout.messages(gone)] == ["DDEATH"]
    assert layout.messages([as_scan(bad("p", "code", ValueDecodeError), group="slow")]) == []
    assert [t for t, *_ in json_layout.messages(gone) if "status" in t]
    back = layout.messages([as_scan(sample("p", "ok", 7), group="default")])
    assert [t.split("/")[2] for t, *_ in back] == ["DBIRTH"]
    assert wire_metrics(back[0][1])["ok"]["value"] == 7


def test_every_group_failing_is_unreachable() -> None:
    layout = SparkplugLayout("plant", "edge1", {"p": [TagConfig("a", "D0", UINT16)]})
    layout.messages([as_scan(sample("p", "a", 1), group="default")])
    out = layout.messages([as_scan(bad("p", "a", ValueDecodeError), group="default")])
    assert [t.split("/")[2] for t, *_ in out] == ["DDEATH"]


def test_a_cold_start_whose_failing_group_reports_first_declares_nothing_dead() -> None:
    """The group of a BCD tag on a word holding 00AFH fails every scan; on a cold start its
    first scan may come in before the good group's (before: DDEATH, then a second DBIRTH, and
    JSON offline then online, within the first seconds)."""
    tags = (TagConfig("ok", "D0", UINT16), TagConfig("code", "D1", BCD16, group="slow"))
    layout = SparkplugLayout("plant", "edge1", {"p": list(tags)})
    groups = scan_groups([PlcConfig("p", "e71+tcp://127.0.0.1:1", tags)])
    assert groups == {"p": frozenset({"default", "slow"})}
    json_layout = JsonLayout("plcstack", "poller", groups=groups)
    layout.will(0.0)  # a session begins: its CONNECT, then the births
    births = [t.split("/")[2] for t, *_ in layout.births(1.0)]
    assert births == ["NBIRTH", "DBIRTH"]
    kinds: list[str] = []
    statuses: list[str] = []
    first_bad: bytes = b""
    for n in range(3):
        for scan in (
            as_scan(bad("p", "code", ValueDecodeError), group="slow"),  # the failing one first
            as_scan(sample("p", "ok", n), group="default"),
        ):
            out = layout.messages([scan])
            kinds += [t.split("/")[2] for t, *_ in out]
            first_bad = first_bad or out[0][1]
            statuses += [
                json.loads(body)["status"]
                for t, body, *_ in json_layout.messages([scan])
                if t.endswith("/status")
            ]
    assert kinds == ["DDATA"] * 6  # no DDEATH, no second DBIRTH
    assert statuses == ["online"]
    code = wire_metrics(first_bad)["code"]  # the bad group's values: null, Quality BAD
    assert code["is_null"] and code["properties"] == {"Quality": 0}


def test_a_cold_start_with_every_group_bad_is_one_death_once_every_group_reported() -> None:
    tags = [TagConfig("a", "D0", BCD16), TagConfig("b", "D1", BCD16, group="slow")]
    layout = SparkplugLayout("plant", "edge1", {"p": tags})
    first = layout.messages([as_scan(bad("p", "a", ValueDecodeError), group="default")])
    assert [t.split("/")[2] for t, *_ in first] == ["DDATA"]  # "slow" may still read fine
    second = layout.messages([as_scan(bad("p", "b", ValueDecodeError), group="slow")])
    assert [t.split("/")[2] for t, *_ in second] == ["DDEATH"]
    assert layout.messages([as_scan(bad("p", "a", ValueDecodeError), group="default")]) == []


async def test_a_host_sees_no_death_when_the_failing_group_is_scanned_first(
    mosquitto: Mosquitto,
) -> None:
    """End to end: a real simulator whose D1 holds 00AFH (no BCD), the failing group scanned
    first, a real broker, the host's view decoded by the specification's field numbers."""
    memory = MelsecMemory()
    memory.write_words("D", 0, [7, 0x00AF])
    sim = await e71.start(memory)
    tags = (TagConfig("code", "D1", BCD16, group="slow"), TagConfig("ok", "D0", UINT16))
    config = PollConfig(
        (PlcConfig("press1", sim.url, tags),), {"slow": 0.05, "default": 0.05}
    )  # fmt: skip
    settings = MqttSettings(
        host=mosquitto.host, port=mosquitto.port, client_id="edge1", mode="sparkplug",
        group_id="plant", reconnect_max=0.2,
    )  # fmt: skip
    try:
        async with (
            subscriber(mosquitto.host, mosquitto.port, "spBv1.0/plant/#") as sub,
            Poller(config) as poller,
            North(poller, NorthConfig(mqtt=settings)) as north,
        ):
            consumer = asyncio.create_task(north.run())
            try:
                await sub.wait_for(
                    lambda s: sum("/DDATA/" in t for t, _ in s.messages) >= 6, timeout=15
                )
            finally:
                consumer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await consumer
    finally:
        await sim.aclose()
    device = [(t.split("/")[2], body) for t, body in sub.messages if t.endswith("/press1")]
    assert [kind for kind, _ in device][:1] == ["DBIRTH"]
    assert {kind for kind, _ in device} == {"DBIRTH", "DDATA"}, [k for k, _ in device]
    assert [kind for kind, _ in device].count("DBIRTH") == 1
    # the failing group did report first, and its metric was null with Quality BAD
    first = wire_metrics(device[1][1])
    assert set(first) == {"code"} and first["code"]["is_null"]
    assert first["code"]["properties"] == {"Quality": 0}
    assert any(wire_metrics(body).get("ok", {}).get("value") == 7 for _, body in device[2:])


# -- on a real broker: QoS, DCMD to an array element, a refused DCMD --------------------------


def test_sparkplug_qos_setting() -> None:
    assert parse_mqtt({}).sparkplug_qos == 0
    assert parse_mqtt({"sparkplug_qos": 1}).sparkplug_qos == 1
    with pytest.raises(ConfigError, match="sparkplug_qos"):
        parse_mqtt({"sparkplug_qos": 2})


@pytest.mark.parametrize("sparkplug_qos", [0, 1])
async def test_a_qos_1_subscriber_sees_the_configured_qos_and_dcmd_writes_an_element(
    mosquitto: Mosquitto, sparkplug_qos: int, caplog: pytest.LogCaptureFixture
) -> None:
    fakes: dict[str, FakeClient] = {}

    def factory(plc: PlcConfig) -> Client:
        fakes[plc.name] = FakeClient(f"fake://{plc.name}")
        return fakes[plc.name]

    tags = (
        TagConfig("speed", "D10", UINT16, writable=True),
        TagConfig("alarms", "M0", BOOL, count=4, writable=True),
        TagConfig("setpoints", "D20", INT16, count=3, writable=True),
    )
    config = PollConfig((PlcConfig("press1", "e71+tcp://127.0.0.1:1", tags),), {"default": 60})
    settings = MqttSettings(
        host=mosquitto.host, port=mosquitto.port, client_id="edge1", mode="sparkplug",
        group_id="plant", reconnect_max=0.2, sparkplug_qos=sparkplug_qos,
    )  # fmt: skip
    async with (
        Poller(config, client_factory=factory) as poller,
        subscriber(mosquitto.host, mosquitto.port, "#", client_id=f"qos{sparkplug_qos}") as sub,
    ):
        layout = SparkplugLayout.for_config(settings, config, poller)
        sink = MqttSink(settings, writes=WritePath(poller), layout=layout)
        await sink.start()
        await sink.wait_connected(5)
        sink.submit([as_scan(sample("press1", "speed", 5))])
        await sub.wait_for(lambda s: any("/DDATA/" in t for t, _ in s.messages))
        kinds = {t.split("/")[2]: q for (t, _), q in zip(sub.messages, sub.qos, strict=True)}
        assert kinds == {"NBIRTH": sparkplug_qos, "DBIRTH": sparkplug_qos, "DDATA": sparkplug_qos}

        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as host:
            cmd = Payload()
            for name, datatype, field, value in (
                ("alarms/2", BOOLEAN_, "boolean_value", True),
                ("setpoints/1", INT16_, "int_value", (-300) & 0xFFFFFFFF),
                ("alarms/9", BOOLEAN_, "boolean_value", True),
            ):
                m = cmd.metrics.add()
                m.name, m.datatype = name, datatype
                setattr(m, field, value)
            with caplog.at_level(logging.WARNING, "plcstack.north.sparkplug"):
                await host.publish("spBv1.0/plant/DCMD/edge1/press1", cmd.SerializeToString())
                await sub.wait_for(lambda s: any("write/resp" in t for t, _ in s.messages))
                await sub.wait_for(lambda _: fakes["press1"].memory["D"][21] != 0)
        memory = fakes["press1"].memory
        assert [memory["M"].get(i, False) for i in range(4)] == [False, False, True, False]
        assert [memory["D"].get(20 + i, 0) for i in range(3)] == [0, (-300) & 0xFFFF, 0]
        refused = [t for t, _ in sub.messages if "write/resp" in t]
        assert refused == ["plcstack/press1/write/resp"]
        assert sink.stats.writes_refused == 1
        # one WARNING, the write path's (tests/test_sparkplug_dcmd_log.py)
        assert "write from sparkplug refused (unknown_tag): press1: write alarms/9" in caplog.text
        await sink.aclose()
