"""Helpers on point lists: a bit of a word, linear scaling, and the fast paths of writes."""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final, Literal

from plcstack.errors import AddressError
from plcstack.values.core import Point, ValueType, as_number, refuse

__all__ = ["Scale", "bits_of_points", "pack_ints", "plain_words"]


# -- a bit of a word ----------------------------------------------------------------------------


def bits_of_points(points: Sequence[Point], point_bits: int, bit: int, count: int) -> list[bool]:
    """``count`` bits from bit ``bit`` of the first point on (bit 0 = least significant), going
    on into the following points: ``D100.F`` then ``D101.0``."""
    out: list[bool] = []
    for k in range(bit, bit + count):
        word, b = divmod(k, point_bits)
        out.append(bool((int(points[word]) >> b) & 1))
    return out


# -- linear scaling -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Scale:
    """Linear scaling of a raw range onto an engineering range (``0..27648 -> 0..100 %``).

    Reading maps ``raw_lo..raw_hi`` onto ``eng_lo..eng_hi`` (values outside extrapolate, so a
    sensor fault stays visible); writing maps back and rounds for integer types.
    """

    raw_lo: float
    raw_hi: float
    eng_lo: float
    eng_hi: float

    def __post_init__(self) -> None:
        for name in ("raw_lo", "raw_hi", "eng_lo", "eng_hi"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise AddressError(f"scale {name} must be a finite number, not {v!r}")
        if self.raw_lo == self.raw_hi or self.eng_lo == self.eng_hi:
            raise AddressError("scale ranges must not be empty (lo == hi)")

    def to_eng(self, raw: float) -> float:
        span = (self.eng_hi - self.eng_lo) / (self.raw_hi - self.raw_lo)
        return self.eng_lo + (raw - self.raw_lo) * span

    def to_raw(self, eng: object, vtype: ValueType[Any]) -> int | float:
        """The raw value for engineering value ``eng``: rounded to an integer for integer and
        BCD types, so the type then checks its range."""
        x = as_number(eng, f"{vtype.name} scaled")
        if not math.isfinite(x):
            raise refuse(eng, f"{vtype.name} scaled", "not a finite number")
        span = (self.raw_hi - self.raw_lo) / (self.eng_hi - self.eng_lo)
        raw = self.raw_lo + (x - self.eng_lo) * span
        return round(raw) if vtype.kind == "int" else raw


# -- fast paths for the point lists of writes ----------------------------------------------------
#
# A 64-word write spent more time validating and packing its values one by one in Python than
# the rest of the request took together. These functions make the same checks with C-level
# builtins (``set(map(type, ...))``, ``struct``, ``min``/``max``) and return ``None`` whenever a
# value is not a plain ``int`` in range, so that the caller's per-value loop still runs and words
# its precise error. ``bool``, ``int`` subclasses and anything not exactly ``int`` take the slow
# path.

_INT: Final = frozenset({int})


def _all_plain_ints(values: object) -> bool:
    return (
        (type(values) is list or type(values) is tuple)
        and len(values) > 0
        and set(map(type, values)) == _INT
    )


def pack_ints(
    values: Sequence[int], order: Literal["<", ">"], code: Literal["H", "B"]
) -> bytes | None:
    """``values`` packed as unsigned ``code`` items (``H`` word, ``B`` byte) in byte ``order``,
    when every value is a plain ``int`` in -32768..65535 (words) or -128..255 (bytes); negatives
    are sent as two's complement. ``None`` otherwise."""
    if not _all_plain_ints(values):
        return None
    fmt = f"{order}{len(values)}{code}"
    try:
        return struct.pack(fmt, *values)  # struct checks the unsigned range itself
    except struct.error:
        pass
    bits = 16 if code == "H" else 8
    if min(values) < -(1 << (bits - 1)) or max(values) >= 1 << bits:
        return None
    mask = (1 << bits) - 1
    return struct.pack(fmt, *[v & mask for v in values])


def plain_words(values: Sequence[int]) -> tuple[int, ...] | None:
    """``values`` as unsigned 16-bit words when all are plain ints in -32768..65535, else None."""
    if not _all_plain_ints(values):
        return None
    low, high = min(values), max(values)
    if low >= 0 and high <= 0xFFFF:
        return tuple(values)
    if low >= -0x8000 and high <= 0xFFFF:
        return tuple([v & 0xFFFF for v in values])
    return None
