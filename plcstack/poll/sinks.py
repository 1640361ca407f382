"""Sample outputs: JSON lines and InfluxDB line protocol, one sample per line.

Both are what ``plcstack poll`` writes to stdout, so it can feed a log shipper or Telegraf's
``execd`` input (``data_format = "influx"``) directly.

JSON lines::

    {"plc": "press1", "tag": "temp", "value": 21.5, "quality": "good",
     "source_time": "2026-11-22T00:31:30.123456Z", "receive_time": "2026-11-22T00:31:30.125002Z"}

A bad sample has ``"value": null`` and an ``"error"`` text. Non-finite floats (a PLC register that
holds a NaN bit pattern) become ``null`` because JSON has no NaN.

InfluxDB line protocol (measurement ``plc``, tags ``plc`` and ``tag``, timestamp = source time in
nanoseconds)::

    plc,plc=press1,tag=temp value=21.5,quality="good" 1795307490123456000
    plc,plc=press1,tag=alarms value_0=true,value_1=false,quality="good" 1795307490123456000
    plc,plc=press1,tag=temp quality="bad",error="press1: read D100 x4: no answer ..." 1795...

Integers carry the ``i`` suffix so Influx stores them as integers; a non-finite float is left out
(line protocol cannot carry it), the ``quality`` field is always there.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from plcstack.poll.engine import Sample
from plcstack.values import Scalar

__all__ = ["FORMATS", "influx_line", "iso_time", "jsonl_line"]


def iso_time(t: float) -> str:
    """Unix seconds as ISO 8601 UTC with microseconds and a ``Z``."""
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


def _json_value(value: Any) -> Any:
    if isinstance(value, list):
        return [_json_value(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def jsonl_line(sample: Sample) -> str:
    record: dict[str, Any] = {
        "plc": sample.plc,
        "tag": sample.tag,
        "value": _json_value(sample.value),
        "quality": sample.quality.value,
        "source_time": iso_time(sample.source_time),
        "receive_time": iso_time(sample.receive_time),
    }
    if sample.error is not None:
        record["error"] = sample.error
    return json.dumps(record, ensure_ascii=False, allow_nan=False)


def _escape_key(text: str) -> str:
    """Measurement names, tag keys and tag values: escape comma, equals and space; no newlines."""
    text = text.replace("\\", "\\\\").replace("\n", " ").replace("\r", " ")
    return text.replace(",", "\\,").replace("=", "\\=").replace(" ", "\\ ")


def _escape_string(text: str) -> str:
    text = text.replace("\n", " ").replace("\r", " ")
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _field(value: Scalar) -> str | None:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"{value}i"
    if isinstance(value, str):
        return _escape_string(value)
    if isinstance(value, tuple):  # KY: the STEP 5 display "12,255"
        return _escape_string(",".join(str(b) for b in value))
    if not math.isfinite(value):
        return None
    return repr(float(value))


def influx_line(sample: Sample, measurement: str = "plc") -> str:
    fields: list[str] = []
    value = sample.value
    if isinstance(value, list):
        for i, item in enumerate(value):
            text = _field(item)
            if text is not None:
                fields.append(f"value_{i}={text}")
    elif value is not None:
        text = _field(value)
        if text is not None:
            fields.append(f"value={text}")
    fields.append(f"quality={_escape_string(sample.quality.value)}")
    if sample.error is not None:
        fields.append(f"error={_escape_string(sample.error)}")
    head = f"{_escape_key(measurement)},plc={_escape_key(sample.plc)},tag={_escape_key(sample.tag)}"
    return f"{head} {','.join(fields)} {round(sample.source_time * 1e6) * 1000}"


#: ``--format`` name -> line formatter
FORMATS: dict[str, Callable[[Sample], str]] = {"jsonl": jsonl_line, "influx": influx_line}
