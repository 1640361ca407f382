"""Output formats: JSON lines and InfluxDB line protocol, golden lines."""

from __future__ import annotations

import json

import pytest

from plcstack.poll.engine import Quality, Sample
from plcstack.poll.sinks import FORMATS, influx_line, iso_time, jsonl_line

T0 = 1795307490.123456
T1 = 1795307490.125


def sample(value: object, quality: Quality = Quality.GOOD, error: str | None = None) -> Sample:
    return Sample("press 1", "temp,a=b", value, quality, T0, T1, error)  # type: ignore[arg-type]


def test_iso_time() -> None:
    assert iso_time(T0) == "2026-11-22T00:31:30.123456Z"


INFLUX = [
    (21.5, 'plc,plc=press\\ 1,tag=temp\\,a\\=b value=21.5,quality="good" 1795307490123456000'),
    (7, 'plc,plc=press\\ 1,tag=temp\\,a\\=b value=7i,quality="good" 1795307490123456000'),
    (True, 'plc,plc=press\\ 1,tag=temp\\,a\\=b value=true,quality="good" 1795307490123456000'),
    (
        [1, -2],
        'plc,plc=press\\ 1,tag=temp\\,a\\=b value_0=1i,value_1=-2i,quality="good" '
        "1795307490123456000",
    ),
    (float("nan"), 'plc,plc=press\\ 1,tag=temp\\,a\\=b quality="good" 1795307490123456000'),
]


@pytest.mark.parametrize(("value", "line"), INFLUX)
def test_influx_good(value: object, line: str) -> None:
    assert influx_line(sample(value)) == line


def test_influx_bad_sample_carries_quoted_error() -> None:
    line = influx_line(sample(None, Quality.BAD, 'p: read D0 x1: "late"\nnext'))
    assert line == (
        'plc,plc=press\\ 1,tag=temp\\,a\\=b quality="bad",error="p: read D0 x1: \\"late\\" next" '
        "1795307490123456000"
    )


def test_jsonl_good_and_bad() -> None:
    good = json.loads(jsonl_line(sample([1.5, float("inf")])))
    assert good == {
        "plc": "press 1",
        "tag": "temp,a=b",
        "value": [1.5, None],
        "quality": "good",
        "source_time": "2026-11-22T00:31:30.123456Z",
        "receive_time": "2026-11-22T00:31:30.125000Z",
    }
    bad = json.loads(jsonl_line(sample(None, Quality.BAD, "p: read D0 x1: no answer")))
    assert bad["value"] is None and bad["quality"] == "bad" and "no answer" in bad["error"]


def test_formats_table() -> None:
    assert set(FORMATS) == {"jsonl", "influx"}
    for fmt in FORMATS.values():
        assert "\n" not in fmt(sample(None, Quality.BAD, "x\ny"))
