"""The Influx ``fields`` layout (a field per tag, typed by the tag; the default) and float32
precision in every output: golden lines, the config key, and acceptance by a real influxd."""

from __future__ import annotations

import json

import pytest

from plcstack.config import parse_config
from plcstack.north.config import parse_north
from plcstack.north.influx import InfluxFormat
from plcstack.north.layout import JsonLayout
from plcstack.poll.config import ConfigError, PlcConfig, TagConfig
from plcstack.poll.samples import Quality, Sample, flatten
from plcstack.poll.sinks import jsonl_line, jsonl_text
from plcstack.values import BOOL, FLOAT32, INT16, KG, KY, UINT16, string
from plcstack.values.points import Scale
from tests.scan_helpers import each
from tests.scan_helpers import scan as as_scan
from tests.servers import Influxd
from tests.test_north_influx import ROOT, poll_example, post, query

T = 1_800_000_000.0
#: -0.1 as a float32 widened to a double (what the poller delivers for a float32 register)
F32 = -0.10000000149011612

PLC = PlcConfig(
    "press1",
    "e71+tcp://127.0.0.1:1",
    (
        TagConfig("strokes", "D0", UINT16),
        TagConfig("force", "D1", FLOAT32),
        TagConfig("level", "D3", INT16, scale=Scale(0, 100, 0, 10)),
        TagConfig("pair", "D4", KY),
        TagConfig("name", "D5", string(6)),
        TagConfig("kg", "D8", KG),
        TagConfig("alarms", "M0", BOOL, count=2),
        TagConfig("temp", "D10", INT16, group="slow"),
    ),
)


def good(tag: str, value: object, t: float = T) -> Sample:
    return Sample("press1", tag, value, Quality.GOOD, t, t + 0.001)  # type: ignore[arg-type]


def test_one_line_per_plc_and_group_one_field_per_tag_typed_by_the_tag() -> None:
    fmt = InfluxFormat([PLC])
    batch = [
        as_scan(
            good("strokes", 1200),
            good("force", F32),
            good("level", 50.0),
            good("pair", (12, 255)),
            good("name", 'a "b"'),
            good("kg", 1.5),
            good("alarms", [True, False]),
        ),
        as_scan(
            Sample("press1", "temp", None, Quality.BAD, T + 1, T + 1.1, "press1: read D10: late"),
            group="slow",
        ),
    ]
    assert fmt.lines(batch) == [
        'plc,plc=press1,group=default strokes=1200i,force=-0.1,level=50.0,pair="12,255",'
        'name="a \\"b\\"",kg=1.5,alarms/0=true,alarms/1=false 1800000000000000000',
        'plc,plc=press1,group=slow plcstack_error="temp: press1: read D10: late"'
        " 1800000001000000000",
    ]
    # an integral engineering value is still a float field; a NaN float32 names itself
    nan = fmt.lines([as_scan(good("level", 5), good("force", float("nan")))])
    assert nan == [
        'plc,plc=press1,group=default level=5.0,plcstack_error="force: non-finite value nan"'
        " 1800000000000000000"
    ]
    # a second scan of the same group in one batch is a line of its own
    assert len(fmt.lines([as_scan(good("strokes", 1)), as_scan(good("strokes", 2, T + 1))])) == 2


def test_float32_at_float32_precision_in_every_output() -> None:
    typed = InfluxFormat([PLC], layout="typed").text(each([good("force", F32), good("level", F32)]))
    assert typed.splitlines()[0].split(" ")[1] == 'value_float=-0.1,quality="good"'
    assert "value_float=-0.10000000149011612" in typed.splitlines()[1]  # a double stays
    assert json.loads(jsonl_line(good("force", F32), float32=True))["value"] == -0.1
    jsonl = jsonl_text([PLC])(each([good("force", F32), good("level", F32)]))
    assert [json.loads(line)["value"] for line in jsonl.splitlines()] == [-0.1, F32]
    layout = JsonLayout("p", "c", 1, float32={("press1", "force")})
    [(_, payload, _, _)] = [
        m for m in layout.messages([as_scan(good("force", F32), group="default")]) if "data" in m[0]
    ]
    assert json.loads(payload)["values"] == {"force": -0.1}


def test_influx_layout_setting() -> None:
    assert parse_north({}).influx_layout == "fields"
    assert parse_north({"influx": {"layout": "typed"}}).influx_layout == "typed"
    with pytest.raises(ConfigError, match='layout must be "fields" or "typed"'):
        parse_north({"influx": {"layout": "wide"}})


async def test_the_fields_layout_loads_into_influxdb(influxd: Influxd) -> None:
    scans = await poll_example()
    samples = flatten(scans)
    text = (ROOT / "plcstack" / "examples" / "plant.toml").read_text()
    lines = InfluxFormat(parse_config(text).plcs).lines(scans)
    influxd.create_database("plant")
    status, body = post(f"{influxd.url}/write?db=plant&precision=ns", "\n".join(lines).encode())
    assert status == 204, body
    keys = {
        row[0]: row[1] for s in query(influxd, "SHOW FIELD KEYS FROM plc") for row in s["values"]
    }
    assert keys["strokes"] == "integer" and keys["temperature"] == "integer"
    assert keys["setpoint"] == "float" and keys["alarms/0"] == "boolean"
    assert keys["plcstack_error"] == "string"  # force holds a NaN: named, not stored
    assert "force" not in keys
    setpoint = query(influxd, "SELECT setpoint FROM plc WHERE \"plc\" = 'oven2' LIMIT 1")
    assert setpoint[0]["values"][0][1] == 20.5
    groups = {
        row[1] for s in query(influxd, 'SHOW TAG VALUES WITH KEY = "group"') for row in s["values"]
    }
    assert groups == {"default", "fast"}
    stored = query(influxd, "SELECT COUNT(temperature) FROM plc")[0]["values"][0][1]
    assert stored == len({s.source_time for s in samples if s.tag == "temperature"})
    print(f"influx fields layout: {len(lines)} lines written, all accepted")
