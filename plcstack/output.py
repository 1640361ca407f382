"""How the command line prints values: the rules a script reading its output can rely on.

- A 32-bit float (``float32``, S5 ``kg``) is printed at float32 precision: the shortest decimal
  that reads back to the same float32 (``3.14``, not the double ``3.140000104904175`` the PLC's
  bits widen to).
- JSON has no NaN or infinity. ``--json`` output and ``poll --format jsonl`` write them as the
  strings ``"NaN"``, ``"Infinity"`` and ``"-Infinity"``, so the line stays valid JSON and the
  value is not lost (a number field that may hold one of these three strings).
"""

from __future__ import annotations

import math
import struct
from typing import Any

__all__ = ["FLOAT32_TYPES", "NON_FINITE", "float32_short", "float32_tags", "json_safe", "shorten"]

_F32 = struct.Struct("<f")

#: the value types whose values are printed at float32 precision (their bits are 32-bit reals)
FLOAT32_TYPES = frozenset({"float32", "kg"})

#: the JSON stand-ins for the floats JSON cannot hold
NON_FINITE = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}


def float32_short(value: float) -> float:
    """The double with the shortest repr that still packs to the same float32 as ``value``.

    ``value`` is returned unchanged when it is not finite or not a float32 to begin with."""
    if not math.isfinite(value):
        return value
    try:
        target = _F32.pack(value)
    except OverflowError:
        return value
    if _F32.unpack(target)[0] != value:
        return value  # not a float32: nothing to shorten
    for digits in range(1, 10):  # 9 significant digits always round-trip a float32
        candidate = float(f"{value:.{digits}g}")
        try:
            if _F32.pack(candidate) == target:
                return candidate
        except OverflowError:  # rounded up beyond the largest float32
            continue
    return value


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats replaced by their strings (lists and tuples walked)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else NON_FINITE[repr(value)]
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def shorten(value: Any) -> Any:
    """``value`` (a float or a list of them) at float32 precision, as :func:`float32_short`."""
    if isinstance(value, float):
        return float32_short(value)
    if isinstance(value, list):
        return [float32_short(v) if isinstance(v, float) else v for v in value]
    return value


def float32_tags(plcs: Any) -> frozenset[tuple[str, str]]:
    """``(plc, tag)`` of every tag of ``plcs`` (poll ``PlcConfig``s) whose values are float32
    reals (``float32``, ``kg``) and not scaled: the ones an output prints at float32 precision."""
    return frozenset(
        (plc.name, tag.name)
        for plc in plcs
        for tag in plc.tags
        if tag.scale is None and tag.type.name in FLOAT32_TYPES
    )
