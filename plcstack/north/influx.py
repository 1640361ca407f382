"""InfluxDB line protocol that InfluxDB 1.x accepts for any mix of tag types.

Influx fixes a field's type per measurement (and shard) by the first point written: a field
``value`` that is an integer for one tag and a float or bool for another is a "field type
conflict" and the whole batch is refused. So the field name says the type::

    plc,plc=press1,tag=strokes value_int=1200i,quality="good" 1795307490123456000
    plc,plc=press1,tag=force value_float=12.5,quality="good" 1795307490123456000
    plc,plc=press1,tag=alarms value_bool_0=true,value_bool_1=false,quality="good" 1795...
    plc,plc=oven2,tag=temp quality="bad",error="oven2: read DB10.DW0 x1: no answer ..." 1795...

* ``value_int`` (``i`` suffix), ``value_float``, ``value_bool``, ``value_str`` (string types such
  as ``string:10``); a tag with ``count > 1`` has
  one field per element, ``value_<type>_<index>``;
* ``quality`` (``"good"``/``"bad"``) always, ``error`` (string) when bad;
* a non-finite float (NaN or infinity in a float32 register) cannot be a field value: the sample
  becomes ``quality="bad"`` with ``error="non-finite value nan"`` (for a list: the finite
  elements stay, the error names the others), never a good sample without a value;
* the measurement name is configurable (``[influx] measurement``), tags are ``plc`` and ``tag``,
  the timestamp is the source time in nanoseconds.

Escaping, as InfluxDB 1.x parses it (checked against influxd 1.6.7 in the tests): in the
measurement a comma and a space get a backslash, in tag keys and values also ``=``; newlines
become spaces. A backslash is *not* an escape character there: ``a\\b`` is stored as written, so
a backslash is written as is, except one that ends a name or precedes a character that gets
escaped: 1.x cannot store that at all (``ab\\`` is "invalid tag format" however it is escaped),
so such a backslash becomes ``_``. In string fields ``\\`` and ``"`` are escaped.
"""

from __future__ import annotations

import math
import re

from plcstack.poll.samples import Quality, Sample

__all__ = ["DEFAULT_MEASUREMENT", "influx_line", "measurement_text", "tag_text"]

DEFAULT_MEASUREMENT = "plc"

_BAD_BACKSLASH_TAG = re.compile(r"\\+(?=[,= ]|$)")
_BAD_BACKSLASH_MEAS = re.compile(r"\\+(?=[, ]|$)")
_NEWLINES = str.maketrans({"\n": " ", "\r": " "})


def _fix_backslashes(text: str, pattern: re.Pattern[str]) -> str:
    return pattern.sub(lambda m: "_" * len(m.group(0)), text)


def measurement_text(name: str) -> str:
    """A measurement name as line protocol (comma and space escaped)."""
    text = _fix_backslashes(name.translate(_NEWLINES), _BAD_BACKSLASH_MEAS)
    return text.replace(",", "\\,").replace(" ", "\\ ") or "_"


def tag_text(text: str) -> str:
    """A tag key or value as line protocol (comma, equals, space escaped); never empty."""
    text = _fix_backslashes(text.translate(_NEWLINES), _BAD_BACKSLASH_TAG)
    return text.replace(",", "\\,").replace("=", "\\=").replace(" ", "\\ ") or "_"


def _string(text: str) -> str:
    text = text.translate(_NEWLINES)
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _field(key: str, value: object, errors: list[str]) -> str | None:
    if isinstance(value, bool):
        return f"{key}_bool={'true' if value else 'false'}"
    if isinstance(value, int):
        return f"{key}_int={value}i"
    if isinstance(value, float):
        if math.isfinite(value):
            return f"{key}_float={value!r}"
        errors.append(f"non-finite value {value!r}")
        return None
    if isinstance(value, str):  # string and KC tags (plcstack.values)
        return f"{key}_str={_string(value)}"
    if isinstance(value, tuple):  # KY: two bytes, as STEP 5 displays them ("12,255")
        return f"{key}_str={_string(','.join(str(b) for b in value))}"
    if isinstance(value, str):
        return f"{key}_str={_string(value)}"
    errors.append(f"value of unsupported type {type(value).__name__}")
    return None


def influx_line(sample: Sample, measurement: str = DEFAULT_MEASUREMENT) -> str:
    """One sample as one line of InfluxDB line protocol (no trailing newline)."""
    fields: list[str] = []
    errors: list[str] = []
    value = sample.value
    good = sample.quality is Quality.GOOD
    if good and isinstance(value, list):
        for i, item in enumerate(value):
            element_errors: list[str] = []
            text = _field("value", item, element_errors)
            if text is not None:
                name, _, rest = text.partition("=")
                fields.append(f"{name}_{i}={rest}")
            errors.extend(f"element {i}: {e}" for e in element_errors)
    elif good and value is not None:
        text = _field("value", value, errors)
        if text is not None:
            fields.append(text)
    error = sample.error
    if errors:
        good = False
        error = "; ".join(errors) if error is None else f"{error}; {'; '.join(errors)}"
    elif good and value is None:
        good, error = False, error or "no value"
    fields.append('quality="good"' if good else 'quality="bad"')
    if error is not None:
        fields.append(f"error={_string(error)}")
    return (
        f"{measurement_text(measurement)},plc={tag_text(sample.plc)},tag={tag_text(sample.tag)}"
        f" {','.join(fields)} {round(sample.source_time * 1e6) * 1000}"
    )
