"""Influx line protocol: golden lines, escaping, and acceptance by a real InfluxDB 1.x (influxd).

The acceptance test polls the shipped example (plcstack/examples/plant.toml, its URLs pointed at
simulators holding a NaN float among ints, floats and bools), writes the whole batch to influxd in
one request and queries every point back: the old layout (one ``value`` field whose type followed
the tag) got "field type conflict" here.
"""

from __future__ import annotations

import asyncio
import json
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from plcstack.config import parse_config
from plcstack.north.influx import influx_line, measurement_text, tag_text
from plcstack.poll.engine import Poller, Quality, Sample
from plcstack.poll.samples import Scan, flatten
from plcstack.sim import e71, s5lan
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.sim.s5memory import S5Memory
from tests.servers import Influxd

ROOT = Path(__file__).resolve().parent.parent


def post(url: str, body: bytes) -> tuple[int, str]:
    request = urllib.request.Request(url, data=body, method="POST")
    try:
        with urllib.request.urlopen(request, timeout=10) as r:
            return int(r.status), r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode()


def query(server: Influxd, q: str, db: str = "plant") -> list[dict[str, Any]]:
    url = f"{server.url}/query?db={db}&q={urllib.parse.quote(q)}"
    with urllib.request.urlopen(url, timeout=10) as r:
        series: list[dict[str, Any]] = json.loads(r.read())["results"][0].get("series", [])
        return series


async def poll_example(scans: int = 7) -> list[Scan]:
    melsec = MelsecMemory()
    melsec.write_words("D", 100, [1200])  # strokes
    melsec.write_words("D", 102, [0x0000, 0x7FC0])  # force: a NaN float32 (low word first)
    melsec.write_bits("M", 0, [True, False, True])
    s5 = S5Memory(default_dbs={10: 16})
    s5.write_db_words(10, 0, [0xFFF6, 0, 0x41A4, 0x0000])  # temperature -10, setpoint 20.5
    sim1 = await e71.start(melsec)
    sim2 = await s5lan.start(s5)
    try:
        text = (ROOT / "plcstack" / "examples" / "plant.toml").read_text()
        text = text.replace("e71+tcp://127.0.0.1:5000", sim1.url)
        text = text.replace("s5lan://127.0.0.1:5010", sim2.url)
        text = text.replace("fast = 0.2", "fast = 0.05").replace(
            "interval = 1.0", "interval = 0.05"
        )
        out: list[Scan] = []
        async with Poller(parse_config(text).poll) as poller:
            async with asyncio.timeout(10):
                async for batch in poller.scans():
                    out.extend(batch)
                    if sum(1 for x in flatten(out) if x.tag == "status") >= scans:
                        break
        return out
    finally:
        await sim1.aclose()
        await sim2.aclose()


async def test_the_example_batch_loads_into_influxdb(influxd: Influxd) -> None:
    samples = flatten(await poll_example())
    kinds = {type(s.value).__name__ for s in samples}
    assert {"int", "float", "list"} <= kinds  # ints, floats (one NaN) and a list of bools
    lines = [influx_line(s) for s in samples]
    influxd.create_database("plant")
    status, body = post(f"{influxd.url}/write?db=plant&precision=ns", "\n".join(lines).encode())
    assert status == 204, body
    stored = query(influxd, "SELECT COUNT(quality) FROM plc")[0]["values"][0][1]
    assert stored == len({(s.plc, s.tag, s.source_time) for s in samples})
    # the NaN float arrived as a bad sample with its reason, the others with typed fields
    force = query(influxd, "SELECT quality, error FROM plc WHERE \"tag\" = 'force' LIMIT 1")
    assert force[0]["values"][0][1:] == ["bad", "non-finite value nan"]
    temp = query(influxd, "SELECT value_int FROM plc WHERE \"tag\" = 'temperature' LIMIT 1")
    assert temp[0]["values"][0][1] == -10
    setpoint = query(influxd, "SELECT value_float FROM plc WHERE \"tag\" = 'setpoint' LIMIT 1")
    assert setpoint[0]["values"][0][1] == 20.5
    alarms = query(
        influxd, "SELECT value_bool_0, value_bool_1 FROM plc WHERE \"tag\" = 'alarms' LIMIT 1"
    )
    assert alarms[0]["values"][0][1:] == [True, False]
    print(f"influx acceptance: {len(lines)} lines written, {stored} points stored, 0 rejected")


NAMES = ["a\\b", "ab\\", "a\\,b", "x y", "k=v", "c,d", "two\\\\", "new\nline", "ü€"]


def test_names_survive_influxdb_escaping(influxd: Influxd) -> None:
    influxd.create_database("plant")
    lines = [
        influx_line(Sample(name, "t", i, Quality.GOOD, 1.0 + i, 1.0 + i), measurement="m " + name)
        for i, name in enumerate(NAMES)
    ]
    status, body = post(f"{influxd.url}/write?db=plant&precision=ns", "\n".join(lines).encode())
    assert status == 204, body
    series = query(influxd, 'SHOW TAG VALUES WITH KEY = "plc"')
    stored = {row[1] for s in series for row in s["values"]}
    # as written, except what InfluxDB 1.x cannot store: a backslash before an escaped character
    # or at the end of a name becomes "_", a newline a space
    expected = {"a\\b", "ab_", "a_,b", "x y", "k=v", "c,d", "two__", "new line", "ü€"}
    assert stored == expected
    measurements = {row[0] for s in query(influxd, "SHOW MEASUREMENTS") for row in s["values"]}
    assert "m a\\b" in measurements and "m ab_" in measurements


@pytest.mark.parametrize(
    ("text", "tag", "measurement"),
    [("a b", "a\\ b", "a\\ b"), ("k=v", "k\\=v", "k=v"), ("e\\", "e_", "e_"), ("", "_", "_")],
)
def test_escaping_golden(text: str, tag: str, measurement: str) -> None:
    assert tag_text(text) == tag
    assert measurement_text(text) == measurement
