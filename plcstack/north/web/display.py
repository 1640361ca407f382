"""A tag's value as an operator reads it: the one formatting of the pages, the event stream
and the REST API's ``text``.

* ``kh`` and ``raw`` words in hexadecimal as the PLC tools write them (``1234h``), ``km`` as
  its bit pattern (``00010010 00110100``), ``ky`` as its two bytes (``18,52``);
* booleans as ``on``/``off``, or the tag's ``labels`` (``closed``/``open``); integers with
  ``labels`` as the state's name;
* floats with the tag's ``decimals``; without, a ``float32``/``kg`` at float32 precision
  (``59.4669``, not the ``59.46688461303711`` its bits widen to) and other floats to ten
  significant digits;
* then the unit (``61.5 °C``). An array shows its first :data:`MAX_SHOWN` values.

The script formats nothing itself: the server sends each text with the value.
"""

from __future__ import annotations

import math
from typing import Any

from plcstack.output import FLOAT32_TYPES, float32_short
from plcstack.poll.config import TagConfig

__all__ = ["MAX_SHOWN", "TagDisplay"]

#: values of an array shown in a cell (the rest is counted)
MAX_SHOWN = 8
_HEX_TYPES = frozenset({"kh", "raw"})


class TagDisplay:
    """How one tag is shown (see the module's docstring)."""

    __slots__ = ("decimals", "float32", "labels", "steps", "type_name", "unit")

    def __init__(self, tag: TagConfig) -> None:
        self.type_name = tag.type.name
        self.unit = tag.unit
        self.decimals = tag.decimals
        self.labels = dict(tag.labels or ())
        self.float32 = self.type_name in FLOAT32_TYPES and tag.scale is None
        #: whether a chart draws the tag as steps between states (a bool, a labelled integer)
        self.steps = tag.type.kind == "bool" or bool(self.labels)

    def text(self, value: Any) -> str:
        """The value with its unit; empty for None (no value yet)."""
        if value is None:
            return ""
        if isinstance(value, list) or (isinstance(value, tuple) and self.type_name != "ky"):
            shown = ", ".join(self.one(v) for v in value[:MAX_SHOWN])
            more = f", ... ({len(value)} values)" if len(value) > MAX_SHOWN else ""
            text = f"[{shown}{more}]"
        else:
            text = self.one(value)
        if self.unit and not (self.labels or isinstance(value, bool)):
            return f"{text} {self.unit}"
        return text

    def one(self, value: Any) -> str:
        """One value, without the unit."""
        if isinstance(value, bool):
            label = self.labels.get(int(value))
            return label if label is not None else ("on" if value else "off")
        if isinstance(value, int):
            label = self.labels.get(value)
            if label is not None:
                return label
            if self.type_name in _HEX_TYPES and value >= 0:
                return f"{value:0{4 if value <= 0xFFFF else 8}X}h"
            if self.type_name == "km" and 0 <= value <= 0xFFFF:
                return f"{value >> 8:08b} {value & 0xFF:08b}"
            return str(value)
        if isinstance(value, float):
            if not math.isfinite(value):
                return "NaN" if math.isnan(value) else ("inf" if value > 0 else "-inf")
            if self.decimals is not None:
                return f"{value:.{self.decimals}f}"
            if self.float32:
                value = float32_short(value)
            return f"{value:.10g}"
        if isinstance(value, tuple) and self.type_name == "ky":
            return ",".join(str(b) for b in value)
        return str(value)

    def chart(self) -> dict[str, Any]:
        """What a chart needs to draw the tag: unit, steps, the names of its states."""
        out: dict[str, Any] = {"unit": self.unit or "", "steps": self.steps}
        if self.labels:
            out["labels"] = {str(k): v for k, v in self.labels.items()}
        elif self.type_name == "bool":
            out["labels"] = {"0": "off", "1": "on"}
        return out
