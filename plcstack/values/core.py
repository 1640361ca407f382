"""The value-type protocol: word and byte order, :class:`ValueType`, and the numeric base that
turns an unsigned integer of ``bits`` bits into points and back. Concrete types: ``types.py``."""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Generic, TypeVar

from plcstack.errors import AddressError, ValueDecodeError, ValueEncodeError

__all__ = [
    "ByteOrder",
    "Endian",
    "Point",
    "Scalar",
    "TagValue",
    "ValueType",
    "WordOrder",
    "default_byte_order",
    "default_word_order",
]

T = TypeVar("T")

#: what a client reads per point: ``bool`` for bit devices, ``int`` for bytes and words
Point = int | bool
#: one decoded value of any type (KY is a pair of bytes, strings and KC are ``str``)
Scalar = int | float | bool | str | tuple[int, int]
#: what a poller sample carries: one scalar, or a list when the tag has ``count > 1``
TagValue = Scalar | list[Scalar]


class Endian(enum.Enum):
    """Which part comes first: the most significant (``BIG``) or the least (``LITTLE``)."""

    BIG = "big"
    LITTLE = "little"


#: order of the points of a multi-point value: BIG = first point most significant (S5),
#: LITTLE = first point least significant (MELSEC: D100 low word, D101 high word)
WordOrder = Endian
#: order of the two bytes of a word when it holds characters: BIG = high byte first (S5 KC),
#: LITTLE = low byte first (MELSEC: "12AB" in D2/D3 reads D2 = 3231H, D3 = 4241H)
ByteOrder = Endian


def default_word_order(scheme: str) -> WordOrder:
    """MELSEC keeps the low word first; every Siemens protocol is big-endian."""
    return Endian.LITTLE if scheme.startswith("e71") else Endian.BIG


def default_byte_order(scheme: str) -> ByteOrder:
    """MELSEC stores the first character in the low byte of a word; S5 in the high byte."""
    return Endian.LITTLE if scheme.startswith("e71") else Endian.BIG


class ValueType(ABC, Generic[T]):
    """One value type: its name, its width and how its points encode a value of type ``T``.

    Instances are immutable and compared by name. ``kind`` says what a consumer that maps types
    onto another system (OPC UA, a historian) needs: ``"bool"``, ``"int"`` (with ``signed`` and
    ``bits``), ``"float"``, ``"text"``, ``"bytes"`` (KY: a pair of bytes) or ``"raw"`` (points
    handed through unchanged).
    """

    __slots__ = ("bits", "kind", "name", "signed", "summary")

    def __init__(self, name: str, bits: int, kind: str, summary: str, signed: bool = False) -> None:
        self.name = name
        #: width of one value in bits (0 for ``raw``: as wide as one point)
        self.bits = bits
        self.kind = kind
        self.signed = signed
        self.summary = summary

    def __repr__(self) -> str:
        return f"<value type {self.name}>"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ValueType) and other.name == self.name

    def __hash__(self) -> int:
        return hash(("ValueType", self.name))

    # -- points -------------------------------------------------------------------------------
    def points_per_value(self, point_bits: int) -> int:
        """How many consecutive points one value occupies in an area of ``point_bits`` points."""
        if point_bits <= 1 or self.bits <= point_bits:
            # Bits are read one point per value; a wider type over a bit area is refused by
            # check_area. A type narrower than a point (int8 in a word) takes the whole point.
            return 1
        return self.bits // point_bits

    def check_area(self, point_bits: int, where: str) -> None:
        """Refuse combinations that cannot be decoded (e.g. ``float32`` over bit points)."""
        if point_bits == 1 and self.kind not in ("raw", "bool"):
            raise AddressError(f"{where}: type {self.name} cannot be read from a bit area")
        if point_bits > 8 and 0 < self.bits < point_bits and self.kind in ("int", "float"):
            # int8/uint8 on a word: which byte is meant? Taking one silently hid the other.
            raise AddressError(
                f"{where}: type {self.name} is {self.bits} bits but the area holds "
                f"{point_bits}-bit words; use a {point_bits}-bit type, or a byte address"
            )
        if point_bits > 1 and self.bits > point_bits and self.bits % point_bits:
            raise AddressError(
                f"{where}: type {self.name} is not a whole number of {point_bits}-bit points"
            )

    @abstractmethod
    def decode(
        self,
        points: Sequence[Point],
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> T:
        """One value from exactly ``points_per_value(point_bits)`` points."""

    @abstractmethod
    def encode(
        self,
        value: object,
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> list[Point]:
        """The points that hold ``value``; :class:`ValueEncodeError` if it cannot be encoded."""

    def decode_many(
        self,
        points: Sequence[Point],
        count: int,
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> list[T]:
        """``count`` values from ``count * points_per_value(point_bits)`` points."""
        n = self.points_per_value(point_bits)
        if len(points) != n * count:
            raise ValueDecodeError(
                f"{count} {self.name} values need {n * count} points, got {len(points)}"
            )
        decode = self.decode
        if n == 1:
            return [decode((p,), point_bits, word_order, byte_order) for p in points]
        return [
            decode(points[i * n : (i + 1) * n], point_bits, word_order, byte_order)
            for i in range(count)
        ]

    def encode_many(
        self,
        values: Sequence[object],
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> list[Point]:
        """The points of all ``values``, every value checked before any point is returned."""
        out: list[Point] = []
        for i, value in enumerate(values):
            try:
                out += self.encode(value, point_bits, word_order, byte_order)
            except ValueEncodeError as exc:
                if len(values) > 1:
                    exc.message = f"value #{i}: {exc.message}"
                raise
        return out


# -- numbers: a raw unsigned integer of ``bits`` bits, split over points by word order ----------


class NumericType(ValueType[T]):
    """A type whose value is a function of one unsigned ``bits``-bit integer."""

    __slots__ = ()

    @abstractmethod
    def from_raw(self, raw: int) -> T:
        """The value of the unsigned ``bits``-bit integer ``raw``."""

    @abstractmethod
    def to_raw(self, value: object) -> int:
        """``value`` as an unsigned ``bits``-bit integer; raises :class:`ValueEncodeError`."""

    def decode(
        self,
        points: Sequence[Point],
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> T:
        width = max(1, point_bits)
        if len(points) == 1:
            raw = int(points[0])
        else:
            mask = (1 << width) - 1
            seq = points if word_order is Endian.BIG else list(reversed(points))
            raw = 0
            for p in seq:
                raw = (raw << width) | (int(p) & mask)
        return self.from_raw(raw & ((1 << self.bits) - 1))

    def encode(
        self,
        value: object,
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> list[Point]:
        raw = self.to_raw(value)
        n = self.points_per_value(point_bits)
        if n == 1:
            return [raw]
        width = point_bits
        mask = (1 << width) - 1
        out: list[Point] = [(raw >> (width * (n - 1 - i))) & mask for i in range(n)]
        if word_order is Endian.LITTLE:
            out.reverse()
        return out


def refuse(value: object, type_name: str, why: str) -> ValueEncodeError:
    """The error for a value a type cannot encode, worded the same by every type."""
    return ValueEncodeError(f"{value!r} cannot be written as {type_name}: {why}")


def as_integer(value: object, type_name: str) -> int:
    """``value`` as an integer for ``type_name``; a bool or a non-integer is refused."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise refuse(value, type_name, "not an integer")
    return value


def as_integer_in(value: object, type_name: str, lo: int, hi: int) -> int:
    """``value`` as an integer ``lo..hi`` for ``type_name``; anything else is refused, in the
    same words for every integer type (the integers, BCD, a raw point)."""
    v = as_integer(value, type_name)
    if not lo <= v <= hi:
        raise refuse(value, type_name, f"outside {lo}..{hi}")
    return v


def as_number(value: object, type_name: str) -> float:
    """``value`` as a float for ``type_name``; a bool, a non-number or an overflow is refused."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise refuse(value, type_name, "not a number")
    try:
        return float(value)
    except OverflowError:
        raise refuse(value, type_name, "too large") from None
