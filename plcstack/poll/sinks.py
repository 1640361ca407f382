"""Sample outputs: JSON lines and InfluxDB line protocol, one sample per line.

Both are what ``plcstack poll`` writes to stdout, so it can feed a log shipper or Telegraf's
``execd`` input (``data_format = "influx"``) directly.

JSON lines::

    {"plc": "press1", "tag": "temp", "value": 21.5, "quality": "good",
     "source_time": "2026-11-22T00:31:30.123456Z", "receive_time": "2026-11-22T00:31:30.125002Z"}

A bad sample has ``"value": null`` and an ``"error"`` text. Non-finite floats (a PLC register that
holds a NaN bit pattern) become ``null`` because JSON has no NaN.

InfluxDB line protocol: see :mod:`plcstack.north.influx` (a field per value type, so InfluxDB 1.x
loads a config that mixes ints, floats and bools; a non-finite float is a bad-quality sample).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Sequence
from datetime import UTC, datetime
from typing import Any

from plcstack.north.influx import influx_line
from plcstack.output import float32_tags, json_safe, shorten
from plcstack.poll.samples import Sample, Scan

__all__ = ["FORMATS", "each_line", "influx_line", "iso_time", "jsonl_line", "jsonl_text"]


def iso_time(t: float) -> str:
    """Unix seconds as ISO 8601 UTC with microseconds and a ``Z``."""
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


def jsonl_line(sample: Sample, *, float32: bool = False) -> str:
    """One sample as a JSON line; ``float32``: the tag is a float32 (or KG), printed at float32
    precision (``-0.1``, not ``-0.10000000149011612``)."""
    value = shorten(sample.value) if float32 else sample.value
    record: dict[str, Any] = {
        "plc": sample.plc,
        "tag": sample.tag,
        "value": json_safe(value),  # NaN/inf as strings: plcstack.output
        "quality": sample.quality.value,
        "source_time": iso_time(sample.source_time),
        "receive_time": iso_time(sample.receive_time),
    }
    if sample.error is not None:
        record["error"] = sample.error
    return json.dumps(record, ensure_ascii=False, allow_nan=False)


def jsonl_text(plcs: Iterable[Any]) -> Callable[[Sequence[Scan]], str]:
    """The JSON lines of a batch of scans (a line per sample), float32 tags of ``plcs`` at
    float32 precision."""
    float32 = float32_tags(plcs)

    def text(scans: Sequence[Scan]) -> str:
        return "".join(
            [
                jsonl_line(s, float32=(s.plc, s.tag) in float32) + "\n"
                for scan in scans
                for s in scan.samples
            ]
        )

    return text


def each_line(line: Callable[[Sample], str], scans: Sequence[Scan]) -> str:
    """``line`` of every sample of ``scans``, each ending in a newline."""
    return "".join([line(s) + "\n" for scan in scans for s in scan.samples])


#: ``--format`` name -> line formatter
FORMATS: dict[str, Callable[[Sample], str]] = {"jsonl": jsonl_line, "influx": influx_line}
