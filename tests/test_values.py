"""The value layer: golden vectors (with their source beside each), round trips, refusals."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from plcstack.errors import AddressError, PlcError, ValueDecodeError, ValueEncodeError
from plcstack.values import (
    BCD16,
    BCD32,
    BOOL,
    FLOAT32,
    INT8,
    INT16,
    INT32,
    KC,
    KF,
    KG,
    KH,
    KT,
    KY,
    KZ,
    RAW,
    TYPES,
    UINT16,
    UINT32,
    Endian,
    Scale,
    ValueType,
    bits_of_points,
    string,
    value_type,
)

BIG, LITTLE = Endian.BIG, Endian.LITTLE
S5_SPEC = "siemens-s5.md Part F"


def s5_words(data: bytes) -> list[int]:
    """S5 memory bytes (high byte first) as the words a client reads."""
    return [int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2)]


# -- KG: (value, bytes in S5 memory order, source) -------------------------------------------
KG_BOTH_WAYS = [
    (10.0, "04 50 00 00", f"{S5_SPEC}, KG worked examples: 10.0"),
    (100.0, "07 64 00 00", f"{S5_SPEC}, KG worked examples: 100.0"),
    (-0.5, "00 C0 00 00", f"{S5_SPEC}, KG worked examples: -0.5"),
    (-1.0, "01 C0 00 00", f"{S5_SPEC}, note on libnodave's negative mantissa: 01 C0 00 00 = -1.0"),
    (0.0, "00 00 00 00", f"{S5_SPEC}, KG row: 0.0 is written 00 00 00 00"),
]
KG_ENCODE_ONLY = [
    (0.1, "FD 66 66 66", f"{S5_SPEC}, KG worked examples: 0.1 (rounded), m = 666666h"),
]
KG_DECODE_ONLY = [
    ("FD 66 66 66", 0.79999995 / 8, f"{S5_SPEC}, KG worked examples: 0.1 reads 0.79999995 x 2^-3"),
    ("7F 00 00 00", 0.0, f"{S5_SPEC}, KG row: any exponent with mantissa 0 reads as 0"),
    ("04 28 00 00", 5.0, f"{S5_SPEC}, KG: non-normalised mantissa 0.3125 x 2^4 must decode"),
]


@pytest.mark.parametrize(("value", "hexbytes", "source"), KG_BOTH_WAYS + KG_ENCODE_ONLY)
def test_kg_encode_golden(value: float, hexbytes: str, source: str) -> None:
    assert KG.encode(value, 16, BIG) == s5_words(bytes.fromhex(hexbytes)), source


@pytest.mark.parametrize(("value", "hexbytes", "source"), KG_BOTH_WAYS)
def test_kg_decode_golden(value: float, hexbytes: str, source: str) -> None:
    assert KG.decode(s5_words(bytes.fromhex(hexbytes)), 16, BIG) == value, source


@pytest.mark.parametrize(("hexbytes", "value", "source"), KG_DECODE_ONLY)
def test_kg_decode_only_golden(hexbytes: str, value: float, source: str) -> None:
    assert KG.decode(s5_words(bytes.fromhex(hexbytes)), 16, BIG) == pytest.approx(value), source


def test_kg_from_bytes_points() -> None:
    # over byte points (MB0..MB3) the same four bytes give the same value
    assert KG.decode(list(bytes.fromhex("04500000")), 8, BIG) == 10.0
    assert KG.encode(10.0, 8, BIG) == [0x04, 0x50, 0, 0]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e39, -2e38, "1.0", True, None])
def test_kg_refuses_what_it_cannot_hold(bad: object) -> None:
    with pytest.raises(ValueEncodeError) as info:
        KG.encode(bad, 16, BIG)
    assert isinstance(info.value, PlcError) and "kg" in info.value.message


@given(st.integers(0, 0xFFFFFFFF))
@example(0x00800000)  # m = -2^23: -1.0, but not normalised (|m / 2^23| = 1); re-encodes 01 C0 00 00
@example(0x00C00000)  # m = -2^22: -0.5, normalised (spec F golden 00 C0 00 00)
@example(0x80000001)  # exponent -128, mantissa 1: below the normalised range
def test_kg_any_bits_decode_to_a_finite_number(raw: int) -> None:
    value = KG.decode([raw >> 16, raw & 0xFFFF], 16, BIG)
    assert math.isfinite(value)
    m = raw & 0xFFFFFF
    # spec F: normalised means 0.5 <= |m / 2^23| < 1, i.e. m in 400000h..7FFFFFh (positive) or
    # -2^23 < m <= -2^22, i.e. 800001h..C00000h (negative); such a pattern re-encodes unchanged
    if 0x400000 <= m <= 0x7FFFFF or 0x800001 <= m <= 0xC00000:
        assert KG.encode(value, 16, BIG) == [raw >> 16, raw & 0xFFFF]
    elif value == 0 or abs(value) >= math.ldexp(0.5, -128):
        # any other pattern re-encodes to the same value, unless it lies below the smallest
        # normalised KG (exponent -128, small mantissa), which rounds to 0 or that smallest
        assert KG.decode(KG.encode(value, 16, BIG), 16, BIG) == value


@given(
    st.floats(allow_nan=False, allow_infinity=False).filter(
        lambda x: x == 0 or 1.5e-39 < abs(x) < 1.7e38
    )
)
def test_kg_round_trip_within_24_bit_precision(x: float) -> None:
    back = KG.decode(KG.encode(x, 16, BIG), 16, BIG)
    assert back == pytest.approx(x, rel=2**-23, abs=0)


def test_kg_tiny_values_round_to_zero_or_the_smallest() -> None:
    smallest = math.ldexp(0.5, -128)
    assert KG.encode(smallest / 3, 16, BIG) == [0, 0]
    assert KG.decode(KG.encode(smallest * 0.75, 16, BIG), 16, BIG) == smallest


# -- KT: (raw word, seconds, source) -----------------------------------------------------------
KT_BOTH_WAYS = [
    (0x2123, 123.0, f"{S5_SPEC}, KT row: 2123h = 123 x 1 s"),
    (0x3999, 9990.0, f"{S5_SPEC}, KT row: max 999 x 10 s"),
    (0x0000, 0.0, f"{S5_SPEC}, KT row: 000 x 0.01 s"),
    (0x0999, 9.99, f"{S5_SPEC}, KT row: base 0 = 0.01 s, 999 counts"),
]
KT_DECODE_ONLY = [
    (0x1050, 5.0, f"{S5_SPEC}, KT row: 1050h = 50 x 0.1 s = 5 s"),
    (0xC123, 1.23, f"{S5_SPEC}, KT row: bits 14-15 ignored when reading"),
]


@pytest.mark.parametrize(("raw", "seconds", "source"), KT_BOTH_WAYS)
def test_kt_golden_both_ways(raw: int, seconds: float, source: str) -> None:
    assert KT.decode([raw], 16) == seconds, source
    assert KT.encode(seconds, 16) == [raw], source


@pytest.mark.parametrize(("raw", "seconds", "source"), KT_DECODE_ONLY)
def test_kt_golden_decode(raw: int, seconds: float, source: str) -> None:
    assert KT.decode([raw], 16) == seconds, source


def test_kt_encoding_takes_the_finest_base_that_holds_the_value() -> None:
    # 5 s fits 500 x 0.01 s: the finest resolution wins over 1050h (same time, coarser base)
    assert KT.encode(5.0, 16) == [0x0500]
    assert KT.encode(12.345, 16) == [0x1123]  # 123 x 0.1 s, rounded to the base
    assert KT.encode(9989.0, 16) == [0x3999]  # rounded to 999 x 10 s


@pytest.mark.parametrize("bad", [9990.5, 10000, -0.01, math.nan, math.inf, "5", None])
def test_kt_refuses_what_it_cannot_hold(bad: object) -> None:
    with pytest.raises(ValueEncodeError):
        KT.encode(bad, 16)


def test_kt_refuses_non_bcd_digits_on_reading() -> None:
    with pytest.raises(ValueDecodeError, match="not BCD"):
        KT.decode([0x20A0], 16)


@given(st.integers(0, 3), st.integers(0, 999))
def test_kt_every_valid_word_round_trips_to_the_same_time(base: int, count: int) -> None:
    digits = int(str(count), 16)
    seconds = KT.decode([(base << 12) | digits], 16)
    assert KT.decode(KT.encode(seconds, 16), 16) == seconds


# -- BCD, KZ ------------------------------------------------------------------------------------
BCD_GOLDEN = [
    (BCD16, [0x1234], 1234, "BCD definition (one decimal digit per nibble); no manual table"),
    (BCD16, [0x9999], 9999, "BCD definition: the largest 4-digit value"),
    (BCD32, [0x5678, 0x1234], 12345678, "BCD definition; MELSEC word order, low word first"),
    (KZ, [0x0999], 999, f"{S5_SPEC}, KZ row: 3 BCD digits 000-999, bits 12-15 zero"),
    (KZ, [0x0042], 42, f"{S5_SPEC}, KZ row"),
]


@pytest.mark.parametrize(("vtype", "points", "value", "source"), BCD_GOLDEN)
def test_bcd_golden_both_ways(vtype: object, points: list[int], value: int, source: str) -> None:
    assert isinstance(vtype, type(BCD16))
    assert vtype.decode(points, 16, LITTLE) == value, source
    assert vtype.encode(value, 16, LITTLE) == points, source


@pytest.mark.parametrize(
    ("vtype", "bad"),
    [(BCD16, 10000), (BCD16, -1), (BCD32, 10**8), (KZ, 1000), (BCD16, 1.0), (KZ, True)],
)
def test_bcd_refuses_what_it_cannot_hold(vtype: object, bad: object) -> None:
    assert isinstance(vtype, type(BCD16))
    with pytest.raises(ValueEncodeError):
        vtype.encode(bad, 16)


def test_bcd_refuses_non_bcd_words() -> None:
    with pytest.raises(ValueDecodeError, match="1A34h"):
        BCD16.decode([0x1A34], 16)


def test_kz_ignores_the_top_nibble_on_reading() -> None:
    assert KZ.decode([0xF123], 16) == 123


@given(st.integers(0, 99_999_999), st.sampled_from([BIG, LITTLE]))
def test_bcd32_round_trip(value: int, order: Endian) -> None:
    assert BCD32.decode(BCD32.encode(value, 16, order), 16, order) == value


# -- IEEE float, integers, word order ----------------------------------------------------------


def test_float32_melsec_golden() -> None:
    # melsec-e71.md §3 rule 10 / seed 003 §10.5.5: D0 = 0000H, D1 = 3F40H is 0.75
    assert FLOAT32.decode([0x0000, 0x3F40], 16, LITTLE) == 0.75
    assert FLOAT32.encode(0.75, 16, LITTLE) == [0x0000, 0x3F40]
    assert FLOAT32.encode(0.75, 16, BIG) == [0x3F40, 0x0000]


def test_float32_refuses_out_of_range_but_keeps_nan() -> None:
    with pytest.raises(ValueEncodeError):
        FLOAT32.encode(1e39, 16)
    assert math.isnan(FLOAT32.decode(FLOAT32.encode(math.nan, 16), 16))


@pytest.mark.parametrize(
    ("vtype", "bad"),
    [(INT16, 32768), (INT16, -32769), (UINT16, -1), (INT8, 128), (UINT32, 2**32), (KF, 1.5)],
)
def test_integers_refuse_out_of_range(vtype: object, bad: object) -> None:
    assert isinstance(vtype, type(INT16))
    with pytest.raises(ValueEncodeError, match=vtype.name):
        vtype.encode(bad, 16)


@pytest.mark.parametrize(
    ("vtype", "point_bits", "lo", "hi", "name"),
    [
        (INT16, 16, -32768, 32767, "int16"),
        (UINT32, 16, 0, 2**32 - 1, "uint32"),
        (BCD16, 16, 0, 9999, "bcd16"),
        (KZ, 16, 0, 999, "kz"),
        # a raw point takes both readings of its bits: signed and unsigned
        (RAW, 16, -32768, 65535, "a 16-bit point"),
        (RAW, 8, -128, 255, "a 8-bit point"),
    ],
)
def test_integer_types_take_their_bounds_and_refuse_past_them_in_one_wording(
    vtype: ValueType[Any], point_bits: int, lo: int, hi: int, name: str
) -> None:
    for edge in (lo, hi):
        points = vtype.encode(edge, point_bits)
        # a raw point reads back unsigned; every other type reads back what was written
        back = edge & ((1 << point_bits) - 1) if vtype is RAW else edge
        assert vtype.decode_many(points, 1, point_bits) == [back]
    for bad in (lo - 1, hi + 1):
        with pytest.raises(ValueEncodeError) as info:
            vtype.encode(bad, point_bits)
        assert info.value.message == f"{bad!r} cannot be written as {name}: outside {lo}..{hi}"


@given(st.integers(-(2**31), 2**31 - 1), st.sampled_from([BIG, LITTLE]), st.sampled_from([8, 16]))
def test_int32_round_trip_any_order_and_point(value: int, order: Endian, bits: int) -> None:
    points = INT32.encode(value, bits, order)
    assert len(points) == 32 // bits
    assert INT32.decode(points, bits, order) == value


def test_int32_word_orders() -> None:
    assert INT32.encode(0x12345678, 16, LITTLE) == [0x5678, 0x1234]  # MELSEC D100 low word
    assert INT32.encode(0x12345678, 16, BIG) == [0x1234, 0x5678]  # S5: high word first
    assert INT32.decode([0xFFFF, 0xFFFF], 16, BIG) == -1


def test_int8_in_a_word_takes_the_low_byte() -> None:
    assert INT8.decode([0x12FF], 16) == -1
    assert INT8.encode(-1, 16) == [0xFF]


def test_s5_formats_kh_km_ky_kc() -> None:
    assert KH.decode([0xBEEF], 16) == 0xBEEF
    # spec F, KY row: two bytes, high byte first, displayed "12,255"
    assert KY.decode([0x0CFF], 16) == (12, 255)
    assert KY.encode((12, 255), 16) == [0x0CFF]
    with pytest.raises(ValueEncodeError):
        KY.encode((256, 0), 16)
    # spec F, KC row: two ASCII characters, high byte first
    assert KC.decode([0x4142], 16) == "AB"
    assert KC.encode("AB", 16) == [0x4142]
    with pytest.raises(ValueEncodeError):
        KC.encode("A", 16)


# -- strings ------------------------------------------------------------------------------------


def test_string_melsec_golden() -> None:
    # melsec-e71.md §3 rule 10 / seed 003 §10.5.5: "12AB" in D2/D3 reads D2 = 3231H, D3 = 4241H
    s = string(4)
    assert s.encode("12AB", 16, LITTLE, LITTLE) == [0x3231, 0x4241]
    assert s.decode([0x3231, 0x4241], 16, LITTLE, LITTLE) == "12AB"
    # the same text on S5 (high byte first)
    assert s.encode("12AB", 16, BIG, BIG) == [0x3132, 0x4142]


def test_string_padding_and_limits() -> None:
    s = string(5)
    assert s.points_per_value(16) == 3
    assert s.encode("ab", 16) == [0x6162, 0, 0]
    assert s.decode([0x6162, 0, 0x4141], 16) == "ab"  # cut at the first NUL
    sp = string(4, pad=" ")
    assert sp.encode("ab", 16) == [0x6162, 0x2020]
    assert sp.decode([0x6162, 0x2020], 16) == "ab"
    assert string(3).encode("abc", 8) == [0x61, 0x62, 0x63]
    with pytest.raises(ValueEncodeError, match="5 characters"):
        s.encode("too long", 16)
    with pytest.raises(ValueEncodeError, match="Latin-1"):
        s.encode("\u20ac", 16)


@given(st.text(st.characters(min_codepoint=1, max_codepoint=255), max_size=9).map(str.rstrip))
def test_string_round_trip(text: str) -> None:
    for order in (BIG, LITTLE):
        s = string(9, pad=" ")
        assert s.decode(s.encode(text, 16, order, order), 16, order, order) == text


# -- names, bits, scaling -----------------------------------------------------------------------


def test_names_are_stable_and_found() -> None:
    assert list(TYPES) == [
        "raw", "bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "float32",
        "bcd16", "bcd32", "kf", "kh", "km", "ky", "kc", "kt", "kz", "kg",
    ]  # fmt: skip
    assert value_type("KG") is KG
    assert value_type("df") is INT32
    assert value_type("string:10") == string(10)
    assert value_type("string:10:space").name == "string:10:space"
    with pytest.raises(AddressError, match="unknown value type 'kq'"):
        value_type("kq")


def test_bits_of_points_run_on_into_the_next_word() -> None:
    assert bits_of_points([0x8000, 0x0001], 16, 15, 2) == [True, True]
    assert bits_of_points([0b1000], 16, 3, 1) == [True]
    assert bits_of_points([0x08], 8, 3, 2) == [True, False]


def test_check_area() -> None:
    with pytest.raises(AddressError, match="bit area"):
        KG.check_area(1, "M0")
    BOOL.check_area(1, "M0")
    RAW.check_area(1, "M0")
    INT32.check_area(8, "MB0")


def test_scale() -> None:
    s = Scale(0, 27648, 0.0, 100.0)
    assert s.to_eng(13824) == 50.0
    assert s.to_raw(50.0, INT16) == 13824
    assert s.to_raw(25.0, FLOAT32) == 6912.0
    with pytest.raises(AddressError):
        Scale(0, 0, 0, 1)
    with pytest.raises(ValueEncodeError):
        s.to_raw(math.nan, INT16)
