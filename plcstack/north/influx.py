"""InfluxDB line protocol, in two layouts (``[influx] layout``).

``layout = "fields"`` (the default): one line per PLC and scan group scan, tags ``plc`` and
``group``, one field per tag named after the tag and typed by the tag's declared type (the
convention of Telegraf's PLC inputs, so a Grafana panel selects a tag by its field name; a tag's
type never changes, so there is no field type conflict)::

    plc,plc=press1,group=fast strokes=1200i,force=12.5,alarms/0=true 1795307490123456000
    plc,plc=oven2,group=default plcstack_error="temp: oven2: read DB10.DW0 x1: no ..." 1795...

* integer types (``int16``, ``uint32``, BCD, ``kf``/``kh``/``km``/``kz``) are integers (``i``);
  ``float32``, ``kg``, ``kt`` and every tag with ``scale`` are floats; ``bool`` (and ``raw`` on
  a bit area) booleans; ``ky`` (``"12,255"``), ``kc`` and ``string:N`` strings;
* a tag with ``count > 1`` has one field per element: ``alarms/0``, ``alarms/1``, ... (the names
  Sparkplug gives them);
* a bad tag, or a non-finite float (NaN in a float32 register), has no field in that line; the
  string field ``plcstack_error`` lists them with the reason (``tag: error; ...``);
* the timestamp is the scan's source time (the earliest of its samples) in nanoseconds.

``layout = "typed"``: the earlier layout, one line per sample with the value in a field named
after its type, so InfluxDB 1.x loads a config that mixes ints, floats and bools into one
``value``-like column::

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

In both, a float32 (and KG) value is printed at float32 precision (``-0.1``, not the
``-0.10000000149011612`` its bits widen to; :func:`plcstack.output.float32_short`).

Escaping, as InfluxDB 1.x parses it (checked against influxd 1.6.7 in the tests): in the
measurement a comma and a space get a backslash, in tag keys, tag values and field keys also
``=``; newlines become spaces. A backslash is *not* an escape character there: ``a\\b`` is
stored as written, so a backslash is written as is, except one that ends a name or precedes a
character that gets escaped: 1.x cannot store that at all (``ab\\`` is "invalid tag format"
however it is escaped), so such a backslash becomes ``_``. In string fields ``\\`` and ``"``
are escaped.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from plcstack.checks import Table
from plcstack.output import FLOAT32_TYPES, float32_short
from plcstack.poll.config import PlcConfig, TagConfig
from plcstack.poll.samples import Quality, Sample, Scan

__all__ = [
    "DEFAULT_LAYOUT",
    "DEFAULT_MEASUREMENT",
    "ERROR_FIELD",
    "LAYOUTS",
    "InfluxFormat",
    "InfluxSettings",
    "influx_line",
    "measurement_text",
    "parse_influx",
    "tag_text",
]

DEFAULT_MEASUREMENT = "plc"
#: ``[influx] layout`` values; the first is the default
LAYOUTS = ("fields", "typed")
DEFAULT_LAYOUT = LAYOUTS[0]
#: the string field of the fields layout that names the bad tags of a line and why
ERROR_FIELD = "plcstack_error"


@dataclass(frozen=True)
class InfluxSettings:
    """The ``[influx]`` table: the measurement and the layout of the lines."""

    measurement: str = DEFAULT_MEASUREMENT
    #: "fields" (a field per tag) or "typed" (a field per value type)
    layout: str = DEFAULT_LAYOUT


def parse_influx(table: object) -> InfluxSettings:
    """``[influx]``: ``measurement`` (default "plc"), ``layout`` ("fields" or "typed")."""
    t = Table.of(table, "influx")
    t.keys(("measurement", "layout"))
    return InfluxSettings(
        t.text("measurement", DEFAULT_MEASUREMENT), t.choice("layout", DEFAULT_LAYOUT, LAYOUTS)
    )


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


def _field(key: str, value: object, errors: list[str], float32: bool = False) -> str | None:
    if isinstance(value, bool):
        return f"{key}_bool={'true' if value else 'false'}"
    if isinstance(value, int):
        return f"{key}_int={value}i"
    if isinstance(value, float):
        if math.isfinite(value):
            return f"{key}_float={(float32_short(value) if float32 else value)!r}"
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


def influx_line(
    sample: Sample, measurement: str = DEFAULT_MEASUREMENT, *, float32: bool = False
) -> str:
    """One sample as one line of the ``typed`` layout (no trailing newline); ``float32``: the
    tag is a float32 (or KG), printed at float32 precision."""
    fields: list[str] = []
    errors: list[str] = []
    value = sample.value
    good = sample.quality is Quality.GOOD
    if good and isinstance(value, list):
        for i, item in enumerate(value):
            element_errors: list[str] = []
            text = _field("value", item, element_errors, float32)
            if text is not None:
                name, _, rest = text.partition("=")
                fields.append(f"{name}_{i}={rest}")
            errors.extend(f"element {i}: {e}" for e in element_errors)
    elif good and value is not None:
        text = _field("value", value, errors, float32)
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


# -- the fields layout ---------------------------------------------------------------------------


def _typed_value(tag: TagConfig | None, value: Any) -> str | None:
    """``value`` as a field value of the type ``tag`` declares; None if it has none (NaN)."""
    kind = tag.type.kind if tag is not None else ""
    name = tag.type.name if tag is not None else ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if tag is not None and (tag.scale is not None or kind == "float"):
        x = float(value)
        if not math.isfinite(x):
            return None
        return repr(float32_short(x) if name in FLOAT32_TYPES else x)
    if isinstance(value, int):
        return f"{value}i"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else None
    if isinstance(value, tuple):  # KY: two bytes, as STEP 5 displays them ("12,255")
        return _string(",".join(str(b) for b in value))
    return _string(str(value))


class InfluxFormat:
    """``plcstack poll --format influx``: a batch of scans as line protocol text, in the
    configured layout (:data:`LAYOUTS`)."""

    def __init__(
        self,
        plcs: Iterable[PlcConfig],
        *,
        layout: str = DEFAULT_LAYOUT,
        measurement: str = DEFAULT_MEASUREMENT,
    ) -> None:
        if layout not in LAYOUTS:
            raise ValueError(f"influx layout must be one of {', '.join(LAYOUTS)}, not {layout!r}")
        self.layout = layout
        self.measurement = measurement
        self._tags = {(plc.name, t.name): t for plc in plcs for t in plc.tags}
        self._head = measurement_text(measurement)

    def text(self, scans: Sequence[Scan]) -> str:
        """The lines of ``scans``, each ending in a newline."""
        if self.layout == "typed":
            tags = self._tags
            return "".join(
                influx_line(s, self.measurement, float32=_is_float32(tags.get((s.plc, s.tag))))
                + "\n"
                for scan in scans
                for s in scan.samples
            )
        return "".join(line + "\n" for line in self.lines(scans))

    def lines(self, scans: Sequence[Scan]) -> list[str]:
        """The ``fields`` layout: one line per scan (a PLC's scan group) in ``scans``."""
        return [self._line(scan) for scan in scans if scan.samples]

    def _line(self, scan: Scan) -> str:
        plc, group = scan.plc, scan.group
        fields: list[str] = []
        errors: list[str] = []
        for s in scan.samples:
            tag = self._tags.get((plc, s.tag))
            if s.quality is not Quality.GOOD or s.value is None:
                errors.append(f"{s.tag}: {s.error or 'no value'}")
                continue
            if isinstance(s.value, list):
                items = [(f"{s.tag}/{i}", v) for i, v in enumerate(s.value)]
            else:
                items = [(s.tag, s.value)]
            for name, value in items:
                text = _typed_value(tag, value)
                if text is None:
                    errors.append(f"{name}: non-finite value {value!r}")
                else:
                    fields.append(f"{tag_text(name)}={text}")
        if errors:
            fields.append(f"{ERROR_FIELD}={_string('; '.join(errors))}")
        when = min(s.source_time for s in scan.samples)
        return (
            f"{self._head},plc={tag_text(plc)},group={tag_text(group)}"
            f" {','.join(fields)} {round(when * 1e6) * 1000}"
        )


def _is_float32(tag: TagConfig | None) -> bool:
    return tag is not None and tag.scale is None and tag.type.name in FLOAT32_TYPES
