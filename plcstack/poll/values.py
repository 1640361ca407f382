"""Tag data types: how the points a client reads become the values a historian stores.

A client returns *points*: bools for bit areas, ints for byte or word areas. A tag of type
``int32`` or ``float32`` spans several points, combined in the PLC family's order: MELSEC keeps the
low word first (D100 = low, D101 = high), Siemens S5 is big-endian throughout (MW10 = MB10 high
byte, MB11 low byte; a double word starts with its high word). ``raw`` hands the points through
unchanged, one value per point, which is the only type that needs no knowledge of the point width.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Sequence

from plcstack.errors import AddressError

__all__ = ["DataType", "Scalar", "TagValue", "WordOrder", "default_word_order"]

#: one decoded value of a tag element
Scalar = int | float | bool
#: what a sample carries: one scalar, or a list when the tag has ``count > 1``
TagValue = Scalar | list[Scalar]


class WordOrder(enum.Enum):
    """Which point of a multi-point value holds the most significant part."""

    #: first point is the most significant (Siemens S5)
    BIG = "big"
    #: first point is the least significant (MELSEC: D100 low word, D101 high word)
    LITTLE = "little"


class DataType(enum.Enum):
    """Tag types of the poller's configuration (``type = "float32"``)."""

    RAW = "raw"
    BOOL = "bool"
    INT8 = "int8"
    UINT8 = "uint8"
    INT16 = "int16"
    UINT16 = "uint16"
    INT32 = "int32"
    UINT32 = "uint32"
    FLOAT32 = "float32"

    @property
    def bits(self) -> int:
        """Width of one value in bits (0 for ``raw``: as wide as one point)."""
        return _BITS[self]

    @property
    def signed(self) -> bool:
        return self in (DataType.INT8, DataType.INT16, DataType.INT32)

    def points_per_value(self, point_bits: int) -> int:
        """How many consecutive points one value occupies in an area of ``point_bits`` points."""
        if self in (DataType.RAW, DataType.BOOL) or point_bits <= 1:
            # Bits are read one point per value; a multi-bit type over a bit area is refused by
            # check_area, so 1 here only matters for RAW and BOOL.
            return 1
        return max(1, self.bits // point_bits)

    def check_area(self, point_bits: int, where: str) -> None:
        """Refuse combinations that cannot be decoded (e.g. ``float32`` over bit points)."""
        if point_bits == 1 and self not in (DataType.RAW, DataType.BOOL):
            raise AddressError(f"{where}: type {self.value} cannot be read from a bit area")
        if point_bits > 1 and self.bits > point_bits and self.bits % point_bits:
            raise AddressError(
                f"{where}: type {self.value} is not a whole number of {point_bits}-bit points"
            )

    def decode(self, points: Sequence[int | bool], point_bits: int, order: WordOrder) -> Scalar:
        """One value from exactly ``points_per_value(point_bits)`` points."""
        if self is DataType.RAW:
            return points[0]
        if self is DataType.BOOL:
            return bool(points[0])
        width = max(1, point_bits)
        mask = (1 << width) - 1
        seq = list(points) if order is WordOrder.BIG else list(reversed(points))
        raw = 0
        for p in seq:
            raw = (raw << width) | (int(p) & mask)
        raw &= (1 << self.bits) - 1
        if self is DataType.FLOAT32:
            value: float = struct.unpack(">f", raw.to_bytes(4, "big"))[0]
            return value
        if self.signed and raw >= 1 << (self.bits - 1):
            raw -= 1 << self.bits
        return raw

    def encode(self, value: object, point_bits: int, order: WordOrder) -> list[int | bool]:
        """The points that write ``value``; raises :class:`AddressError` if it does not fit."""
        if self is DataType.BOOL or (self is DataType.RAW and point_bits == 1):
            if not isinstance(value, bool | int) or value not in (0, 1):
                raise AddressError(f"value {value!r} is not a bit (true/false)")
            return [bool(value)]
        if self is DataType.FLOAT32:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise AddressError(f"value {value!r} is not a number")
            fval = float(value)
            if math.isfinite(fval) and abs(fval) > 3.4028234663852886e38:
                raise AddressError(f"value {value!r} is out of range for float32")
            raw = int.from_bytes(struct.pack(">f", fval), "big")
        else:
            if isinstance(value, bool) or not isinstance(value, int):
                raise AddressError(f"value {value!r} is not an integer")
            bits = point_bits if self is DataType.RAW else self.bits
            lo = -(1 << (bits - 1)) if self.signed or self is DataType.RAW else 0
            hi = (1 << bits) - 1 if not self.signed else (1 << (bits - 1)) - 1
            if not lo <= value <= hi:
                raise AddressError(f"value {value} is outside {lo}..{hi} for {self.value}")
            raw = value & ((1 << bits) - 1)
            if self is DataType.RAW:
                return [raw]
        n = self.points_per_value(point_bits)
        width = max(1, point_bits)
        mask = (1 << width) - 1
        out: list[int | bool] = [(raw >> (width * (n - 1 - i))) & mask for i in range(n)]
        if order is WordOrder.LITTLE:
            out.reverse()
        return out


_BITS = {
    DataType.RAW: 0,
    DataType.BOOL: 1,
    DataType.INT8: 8,
    DataType.UINT8: 8,
    DataType.INT16: 16,
    DataType.UINT16: 16,
    DataType.INT32: 32,
    DataType.UINT32: 32,
    DataType.FLOAT32: 32,
}


def default_word_order(scheme: str) -> WordOrder:
    """MELSEC keeps the low word first; every Siemens protocol is big-endian."""
    return WordOrder.LITTLE if scheme.startswith("e71") else WordOrder.BIG
