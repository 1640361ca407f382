"""The value types: integers, IEEE float, BCD, the S5 formats (spec siemens-s5.md Part F) and
fixed-length text, as module constants and by name (:func:`value_type`)."""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Sequence
from typing import Any, Final, Literal

from plcstack.errors import AddressError, ValueDecodeError
from plcstack.values.core import (
    ByteOrder,
    Endian,
    NumericType,
    Point,
    ValueType,
    WordOrder,
    as_integer_in,
    as_number,
    refuse,
)

__all__ = [
    "BCD16",
    "BCD32",
    "BOOL",
    "FLOAT32",
    "INT8",
    "INT16",
    "INT32",
    "KC",
    "KF",
    "KG",
    "KH",
    "KM",
    "KT",
    "KT_MAX_SECONDS",
    "KY",
    "KZ",
    "RAW",
    "TYPES",
    "UINT8",
    "UINT16",
    "UINT32",
    "string",
    "value_type",
]


class _Int(NumericType[int]):
    __slots__ = ("_hi", "_lo")

    def __init__(self, name: str, bits: int, signed: bool, summary: str) -> None:
        super().__init__(name, bits, "int", summary, signed)
        self._lo = -(1 << (bits - 1)) if signed else 0
        self._hi = (1 << (bits - 1)) - 1 if signed else (1 << bits) - 1

    def from_raw(self, raw: int) -> int:
        if self.signed and raw >= 1 << (self.bits - 1):
            return raw - (1 << self.bits)
        return raw

    def to_raw(self, value: object) -> int:
        return as_integer_in(value, self.name, self._lo, self._hi) & ((1 << self.bits) - 1)


class _Float32(NumericType[float]):
    __slots__ = ()

    def from_raw(self, raw: int) -> float:
        value: float = struct.unpack(">f", raw.to_bytes(4, "big"))[0]
        return value

    def to_raw(self, value: object) -> int:
        f = as_number(value, self.name)
        try:
            return int.from_bytes(struct.pack(">f", f), "big")
        except OverflowError:
            raise refuse(value, self.name, "beyond +-3.4e38") from None


#: smallest normalised KG magnitude: mantissa 0.5, exponent -128
_KG_MIN: Final = math.ldexp(0.5, -128)


class _KG(NumericType[float]):
    """S5 KG real (spec F): byte 0 exponent (two's complement), bytes 1-3 mantissa (24-bit two's
    complement), value = m / 2^23 * 2^e. No NaN, no infinity."""

    __slots__ = ()

    def from_raw(self, raw: int) -> float:
        e = raw >> 24
        if e >= 0x80:
            e -= 0x100
        m = raw & 0xFFFFFF
        if m >= 0x800000:
            m -= 0x1000000  # a true two's complement (libnodave forgets the +1: spec F)
        return math.ldexp(m, e - 23)

    def to_raw(self, value: object) -> int:
        x = as_number(value, self.name)
        if not math.isfinite(x):
            raise refuse(value, self.name, "KG has no NaN or infinity")
        if x == 0.0:
            return 0
        if abs(x) < _KG_MIN:
            # below the smallest normalised KG: round to the nearer of 0 and +-_KG_MIN
            if abs(x) < _KG_MIN / 2:
                return 0
            x = math.copysign(_KG_MIN, x)
        frac, e = math.frexp(x)  # x = frac * 2^e, 0.5 <= |frac| < 1
        m = round(frac * (1 << 23))
        if abs(m) == 1 << 23:  # rounding carried into the next binade: renormalise
            m //= 2
            e += 1
        if e > 127:
            raise refuse(value, self.name, "beyond the KG range (about +-1.7e38)")
        return ((e & 0xFF) << 24) | (m & 0xFFFFFF)


def _bcd_digits(raw: int, digits: int, type_name: str) -> int:
    value = 0
    for i in reversed(range(digits)):
        nibble = (raw >> (4 * i)) & 0xF
        if nibble > 9:
            raise ValueDecodeError(
                f"{raw:0{digits}X}h is not {type_name}: digit {nibble:X}h is not BCD (0-9)"
            )
        value = value * 10 + nibble
    return value


def _to_bcd(value: int, digits: int) -> int:
    raw = 0
    for i in range(digits):
        raw |= (value % 10) << (4 * i)
        value //= 10
    return raw


class _BCD(NumericType[int]):
    """Unsigned BCD, 4 digits per word (MELSEC BCD16/BCD32, S5 KZ with 3 digits)."""

    __slots__ = ("_digits",)

    def __init__(self, name: str, bits: int, digits: int, summary: str) -> None:
        super().__init__(name, bits, "int", summary)
        self._digits = digits

    def from_raw(self, raw: int) -> int:
        # KZ: bits 12-15 carry no digit; they are ignored on reading (spec F writes them 0)
        return _bcd_digits(raw, self._digits, self.name)

    def to_raw(self, value: object) -> int:
        v = as_integer_in(value, self.name, 0, 10**self._digits - 1)
        return _to_bcd(v, self._digits)


#: KT time bases (bits 12-13): seconds per count as (numerator, denominator)
_KT_BASES: Final = ((1, 100), (1, 10), (1, 1), (10, 1))
#: the longest time KT can hold: 999 x 10 s
KT_MAX_SECONDS: Final = 9990.0


class _KT(NumericType[float]):
    """S5 KT timer value in seconds (spec F): 3 BCD digits and a time base 0.01/0.1/1/10 s.
    Encoding picks the finest base that holds the value and rounds to it."""

    __slots__ = ()

    def from_raw(self, raw: int) -> float:
        count = _bcd_digits(raw & 0xFFF, 3, self.name)
        num, den = _KT_BASES[(raw >> 12) & 0x3]  # bits 14-15 ignored when reading
        return count * num / den  # division keeps 0.1-steps at their nearest double

    def to_raw(self, value: object) -> int:
        seconds = as_number(value, self.name)
        if not math.isfinite(seconds) or seconds < 0:
            raise refuse(value, self.name, "a time must be a finite number >= 0 seconds")
        if seconds > KT_MAX_SECONDS:
            raise refuse(value, self.name, "beyond 999 x 10 s, the longest S5 time")
        for base, (num, den) in enumerate(_KT_BASES):
            count = round(seconds * den / num)
            if count <= 999:
                return (base << 12) | _to_bcd(count, 3)
        raise AssertionError("unreachable: 9990 s fits base 3")  # pragma: no cover


class _Bool(NumericType[bool]):
    __slots__ = ()

    def from_raw(self, raw: int) -> bool:
        return raw != 0

    def to_raw(self, value: object) -> int:
        if not isinstance(value, int) or value not in (0, 1):
            raise refuse(value, self.name, "not a bit (true/false or 1/0)")
        return int(value)

    def decode(
        self,
        points: Sequence[Point],
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> bool:
        # a bit point, or a whole word/byte taken as "not zero"
        return bool(points[0])

    def encode(
        self,
        value: object,
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> list[Point]:
        bit = bool(self.to_raw(value))
        return [bit] if point_bits <= 1 else [int(bit)]


class _Raw(ValueType[int | bool]):
    """The points unchanged, one value per point: the only type that needs no point width."""

    __slots__ = ()

    def decode(
        self,
        points: Sequence[Point],
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> int | bool:
        return points[0]

    def encode(
        self,
        value: object,
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> list[Point]:
        if point_bits <= 1:
            return BOOL.encode(value, 1)
        lo, hi = -(1 << (point_bits - 1)), (1 << point_bits) - 1
        return [as_integer_in(value, f"a {point_bits}-bit point", lo, hi) & hi]


class _KY(NumericType[tuple[int, int]]):
    """S5 KY: the two bytes of a word, high byte first (spec F: displayed "12,255")."""

    __slots__ = ()

    def from_raw(self, raw: int) -> tuple[int, int]:
        return raw >> 8, raw & 0xFF

    def to_raw(self, value: object) -> int:
        if (
            not isinstance(value, tuple | list)
            or len(value) != 2
            or not all(type(b) is int and 0 <= b <= 255 for b in value)
        ):
            raise refuse(value, self.name, "not a pair of bytes (0..255, 0..255)")
        high, low = int(value[0]), int(value[1])
        return (high << 8) | low


# -- text: bytes taken from the words in byte order ---------------------------------------------


class _Text(ValueType[str]):
    """Fixed-length characters, two per word (byte order) or one per byte point.

    Reading cuts at the first NUL and strips trailing padding; writing pads to ``length`` with
    ``pad`` (NUL or space) and refuses text that is too long or has characters outside Latin-1.
    """

    __slots__ = ("length", "pad", "strip")

    def __init__(self, name: str, length: int, pad: str, strip: bool, summary: str) -> None:
        super().__init__(name, 8 * length, "text", summary)
        self.length = length
        self.pad = pad
        self.strip = strip

    def points_per_value(self, point_bits: int) -> int:
        if point_bits <= 1:
            return 1
        return -(-self.bits // point_bits)  # an odd length still takes its whole last word

    def check_area(self, point_bits: int, where: str) -> None:
        if point_bits not in (8, 16):
            raise AddressError(f"{where}: text needs a byte or word area")

    def decode(
        self,
        points: Sequence[Point],
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> str:
        if point_bits == 16:
            order: Literal["big", "little"] = "big" if byte_order is Endian.BIG else "little"
            data = b"".join((int(p) & 0xFFFF).to_bytes(2, order) for p in points)
        else:
            data = bytes(int(p) & 0xFF for p in points)
        data = data[: self.length]
        if not self.strip:
            return data.decode("latin-1")
        text = data.split(b"\0", 1)[0].decode("latin-1")
        return text.rstrip(" ") if self.pad == " " else text

    def encode(
        self,
        value: object,
        point_bits: int,
        word_order: WordOrder = Endian.BIG,
        byte_order: ByteOrder = Endian.BIG,
    ) -> list[Point]:
        if not isinstance(value, str):
            raise refuse(value, self.name, "not a string")
        try:
            data = value.encode("latin-1")
        except UnicodeEncodeError:
            raise refuse(value, self.name, "has characters outside Latin-1") from None
        if len(data) > self.length or (not self.strip and len(data) != self.length):
            raise refuse(value, self.name, f"needs exactly {self.length} characters or fewer"
                          if self.strip else f"needs exactly {self.length} characters")  # fmt: skip
        size = self.points_per_value(point_bits) * (point_bits // 8)
        data = data.ljust(size, self.pad.encode("latin-1"))
        if point_bits == 16:
            worder: Literal["big", "little"] = "big" if byte_order is Endian.BIG else "little"
            return [int.from_bytes(data[i : i + 2], worder) for i in range(0, len(data), 2)]
        return list(data)


# -- the types ----------------------------------------------------------------------------------

RAW: Final[ValueType[int | bool]] = _Raw("raw", 0, "raw", "each point unchanged (bool or int)")
BOOL: Final[ValueType[bool]] = _Bool("bool", 1, "bool", "a bit (bit device, or a bit of a word)")
INT8: Final[ValueType[int]] = _Int("int8", 8, True, "-128..127")
UINT8: Final[ValueType[int]] = _Int("uint8", 8, False, "0..255")
INT16: Final[ValueType[int]] = _Int("int16", 16, True, "-32768..32767")
UINT16: Final[ValueType[int]] = _Int("uint16", 16, False, "0..65535")
INT32: Final[ValueType[int]] = _Int("int32", 32, True, "two words, word order of the PLC")
UINT32: Final[ValueType[int]] = _Int("uint32", 32, False, "two words, word order of the PLC")
FLOAT32: Final[ValueType[float]] = _Float32("float32", 32, "float", "IEEE 754 single, two words")
BCD16: Final[ValueType[int]] = _BCD("bcd16", 16, 4, "4 BCD digits, 0..9999")
BCD32: Final[ValueType[int]] = _BCD("bcd32", 32, 8, "8 BCD digits in two words, 0..99999999")
KF: Final[ValueType[int]] = _Int("kf", 16, True, "S5 fixed point, -32768..32767")
KH: Final[ValueType[int]] = _Int("kh", 16, False, "S5 hex word, 0..FFFFh")
KM: Final[ValueType[int]] = _Int("km", 16, False, "S5 bit pattern of a word")
KY: Final[ValueType[tuple[int, int]]] = _KY("ky", 16, "bytes", "S5 two bytes (high, low)")
KC: Final[ValueType[str]] = _Text("kc", 2, " ", False, "S5 two characters, high byte first")
KT: Final[ValueType[float]] = _KT("kt", 16, "float", "S5 timer: 3 BCD digits x time base, s")
KZ: Final[ValueType[int]] = _BCD("kz", 16, 3, "S5 counter: 3 BCD digits, 0..999")
KG: Final[ValueType[float]] = _KG("kg", 32, "float", "S5 real: 8-bit exponent, 24-bit mantissa")

#: every fixed type by name (strings are made by :func:`string`)
TYPES: Final[dict[str, ValueType[Any]]] = {
    t.name: t
    for t in (
        *(RAW, BOOL, INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, BCD16, BCD32),
        *(KF, KH, KM, KY, KC, KT, KZ, KG),
    )
}
#: other names for the same types: S5 double-word formats (spec F: DH hex, DF two's complement)
_ALIASES: Final[dict[str, ValueType[Any]]] = {
    "dh": UINT32,
    "df": INT32,
    "real": FLOAT32,
    "float": FLOAT32,
}

_PADS: Final = {"nul": "\0", "space": " "}


def string(length: int, pad: str = "\0") -> ValueType[str]:
    """Text of ``length`` characters (Latin-1), padded with ``pad`` (``"\\0"`` or ``" "``)."""
    if isinstance(length, bool) or not isinstance(length, int) or not 1 <= length <= 4096:
        raise AddressError(f"string length must be 1..4096, not {length!r}")
    if pad not in ("\0", " "):
        raise AddressError(f"string padding must be NUL or space, not {pad!r}")
    name = f"string:{length}" + (":space" if pad == " " else "")
    summary = f"{length} characters, {'space' if pad == ' ' else 'NUL'}-padded"
    return _Text(name, length, pad, True, summary)


_STRING_NAME: Final = re.compile(r"^string:(\d{1,4})(?::(nul|space))?$")


def value_type(name: str | ValueType[Any]) -> ValueType[Any]:
    """The type called ``name`` (case-insensitive); raises :class:`AddressError` naming the
    known types. ``string:N`` is N characters NUL-padded, ``string:N:space`` space-padded."""
    if isinstance(name, ValueType):
        return name
    if not isinstance(name, str):
        raise AddressError(f"a value type is a name like 'int16', not {name!r}")
    key = name.strip().lower()
    found = TYPES.get(key) or _ALIASES.get(key)
    if found is not None:
        return found
    m = _STRING_NAME.match(key)
    if m:
        return string(int(m.group(1)), _PADS[m.group(2) or "nul"])
    if key.split(":")[0] in ("string", "str", "text"):  # "string" without its length
        raise AddressError(
            f"value type {name!r}: a string type says its length in characters, "
            "string:N (NUL-padded) or string:N:space, e.g. string:20"
        )
    raise AddressError(f"unknown value type {name!r}; types: {', '.join(TYPES)}, string:N[:space]")
