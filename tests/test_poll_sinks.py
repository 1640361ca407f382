"""Output formats: JSON lines and InfluxDB line protocol, golden lines."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.poll.engine import Quality, Sample
from plcstack.poll.sinks import FORMATS, influx_line, iso_time, jsonl_line

T0 = 1795307490.123456
T1 = 1795307490.125


def sample(value: object, quality: Quality = Quality.GOOD, error: str | None = None) -> Sample:
    return Sample("press 1", "temp,a=b", value, quality, T0, T1, error)  # type: ignore[arg-type]


def test_iso_time() -> None:
    assert iso_time(T0) == "2026-11-22T00:31:30.123456Z"


# A field per value type (InfluxDB 1.x fixes a field's type per measurement), see north.influx.
H = "plc,plc=press\\ 1,tag=temp\\,a\\=b "
INFLUX = [
    (21.5, H + 'value_float=21.5,quality="good" 1795307490123456000'),
    (7, H + 'value_int=7i,quality="good" 1795307490123456000'),
    (True, H + 'value_bool=true,quality="good" 1795307490123456000'),
    ([1, -2], H + 'value_int_0=1i,value_int_1=-2i,quality="good" 1795307490123456000'),
    ('a "b"\\', H + 'value_str="a \\"b\\"\\\\",quality="good" 1795307490123456000'),
    (float("nan"), H + 'quality="bad",error="non-finite value nan" 1795307490123456000'),
    (
        [1.5, float("-inf")],
        H + 'value_float_0=1.5,quality="bad",error="element 1: non-finite value -inf" '
        "1795307490123456000",
    ),
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
        "value": [1.5, "Infinity"],  # the documented rule (plcstack.output)
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


_SCALARS = st.one_of(st.integers(-(2**31), 2**32), st.booleans(), st.floats(width=32))


@settings(max_examples=200, deadline=None)
@given(
    plc=st.text(min_size=1),
    tag=st.text(min_size=1),
    value=st.one_of(st.none(), _SCALARS, st.lists(_SCALARS, min_size=1, max_size=5)),
    error=st.one_of(st.none(), st.text()),
    t=st.floats(0, 4e9),
)
def test_any_sample_is_one_well_formed_line(
    plc: str, tag: str, value: object, error: str | None, t: float
) -> None:
    quality = Quality.GOOD if error is None and value is not None else Quality.BAD
    s = Sample(plc, tag, value, quality, t, t, error)  # type: ignore[arg-type]
    record = json.loads(jsonl_line(s))
    assert (record["plc"], record["tag"], record["quality"]) == (plc, tag, quality.value)
    assert record.get("error") == error
    line = influx_line(s)
    assert "\n" not in line and "\r" not in line
    assert line.startswith("plc,plc=") and line.endswith(str(round(t * 1e6) * 1000))
    finite = all(
        not isinstance(v, float) or math.isfinite(v)
        for v in (value if isinstance(value, list) else [value])
    )
    assert f'quality="{quality.value if finite else "bad"}"' in line
