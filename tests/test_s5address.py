"""S5 operand notation shared by S5-LAN, AS511 and FETCH/WRITE."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.errors import AddressError
from plcstack.s5address import FETCHWRITE_ORG, S5Address, S5Area, S5Unit, parse_s5_address

A, U = S5Area, S5Unit

GOOD = [
    # text, area, unit, offset, db, byte_offset, canonical
    ("DB10.DW5", A.DB, U.WORD, 5, 10, 10, "DB10.DW5"),
    ("db10.dw5", A.DB, U.WORD, 5, 10, 10, "DB10.DW5"),
    (" DB1.DW0 ", A.DB, U.WORD, 0, 1, 0, "DB1.DW0"),
    ("DX3.DW0", A.DX, U.WORD, 0, 3, 0, "DX3.DW0"),
    ("DB255.DW2047", A.DB, U.WORD, 2047, 255, 4094, "DB255.DW2047"),
    ("DB10.DL5", A.DB, U.BYTE, 10, 10, 10, "DB10.DL5"),
    ("DB10.DR5", A.DB, U.BYTE, 11, 10, 11, "DB10.DR5"),
    ("DB10.DBB3", A.DB, U.BYTE, 3, 10, 3, "DB10.DR1"),
    ("MB100", A.FLAGS, U.BYTE, 100, None, 100, "MB100"),
    ("MW10", A.FLAGS, U.WORD, 10, None, 10, "MW10"),
    ("IB0", A.INPUTS, U.BYTE, 0, None, 0, "EB0"),
    ("EB0", A.INPUTS, U.BYTE, 0, None, 0, "EB0"),
    ("IW4", A.INPUTS, U.WORD, 4, None, 4, "EW4"),
    ("EW4", A.INPUTS, U.WORD, 4, None, 4, "EW4"),
    ("QB0", A.OUTPUTS, U.BYTE, 0, None, 0, "AB0"),
    ("AB7", A.OUTPUTS, U.BYTE, 7, None, 7, "AB7"),
    ("QW2", A.OUTPUTS, U.WORD, 2, None, 2, "AW2"),
    ("AW2", A.OUTPUTS, U.WORD, 2, None, 2, "AW2"),
    ("T5", A.TIMERS, U.WORD, 5, None, 10, "T5"),
    ("C5", A.COUNTERS, U.WORD, 5, None, 10, "Z5"),
    ("Z5", A.COUNTERS, U.WORD, 5, None, 10, "Z5"),
    ("t0", A.TIMERS, U.WORD, 0, None, 0, "T0"),
]


@pytest.mark.parametrize(("text", "area", "unit", "offset", "db", "byte_off", "canon"), GOOD)
def test_parse_good(
    text: str,
    area: S5Area,
    unit: S5Unit,
    offset: int,
    db: int | None,
    byte_off: int,
    canon: str,
) -> None:
    addr = parse_s5_address(text)
    assert addr == S5Address(area, unit, offset, db)
    assert addr.byte_offset == byte_off
    assert str(addr) == canon
    assert parse_s5_address(str(addr)) == addr


BAD = [
    ("", "not an S5 address"),
    ("D100", "not an S5 address"),
    ("DB10", "not an S5 address"),
    ("DB10.DBW10", "DB10.DW5"),
    ("DB10.DBW11", "DB10.DR5"),
    ("DB0.DW1", "not a data block"),
    ("DB256.DW1", "1..255"),
    ("DB10.DW70000", "0..65535"),
    ("DB10.DBX1.0", "bit operand is not a point: read it as a bool (--type bool"),
    ("DB10.D1.0", "bit operand is not a point: read it as a bool (--type bool"),
    ("DB10.DBD0", "double words"),
    ("M10.3", "bit operand is not a point: read it as a bool (--type bool"),
    ("M10", "MB10"),
    ("MD4", "double words"),
    ("MB-1", "not an S5 address"),
    ("MB 1", "not an S5 address"),
    ("TW5", "not an S5 address"),
    ("PB0", "not an S5 address"),
    ("MB123456", "not an S5 address"),
]


@pytest.mark.parametrize(("text", "fragment"), BAD)
def test_parse_bad(text: str, fragment: str) -> None:
    with pytest.raises(AddressError) as err:
        parse_s5_address(text)
    assert fragment in str(err.value)
    assert repr(text) in str(err.value)


def test_not_a_string() -> None:
    with pytest.raises(AddressError):
        parse_s5_address(5)  # type: ignore[arg-type]


def test_shift_and_lengths() -> None:
    assert parse_s5_address("MW10").shifted(1) == parse_s5_address("MW12")
    assert parse_s5_address("MB10").shifted(3) == parse_s5_address("MB13")
    assert parse_s5_address("DB1.DW5").shifted(2) == parse_s5_address("DB1.DW7")
    assert parse_s5_address("T5").shifted(1) == parse_s5_address("T6")
    assert parse_s5_address("MW10").byte_length(3) == 6
    assert parse_s5_address("MB10").byte_length(3) == 3


def test_dataclass_rules() -> None:
    with pytest.raises(AddressError):
        S5Address(A.TIMERS, U.BYTE, 1)
    with pytest.raises(AddressError):
        S5Address(A.FLAGS, U.BYTE, 1, db=3)
    with pytest.raises(AddressError):
        S5Address(A.DB, U.WORD, 1)
    assert FETCHWRITE_ORG[A.DX] == 0x0A
    assert parse_s5_address("C3").to_str(english=True) == "C3"
    assert parse_s5_address("EB3").to_str(english=True) == "IB3"


@settings(max_examples=200)
@given(st.text(max_size=16))
def test_random_text_only_address_error(text: str) -> None:
    try:
        addr = parse_s5_address(text)
    except AddressError:
        return
    assert parse_s5_address(str(addr)) == addr


_addresses = st.one_of(
    st.builds(
        S5Address,
        st.sampled_from([A.DB, A.DX]),
        st.sampled_from(list(U)),
        st.integers(0, 0xFFFF),
        st.integers(1, 255),
    ),
    st.builds(
        S5Address,
        st.sampled_from([A.FLAGS, A.INPUTS, A.OUTPUTS]),
        st.sampled_from(list(U)),
        st.integers(0, 0xFFFF),
    ),
    st.builds(
        S5Address,
        st.sampled_from([A.TIMERS, A.COUNTERS]),
        st.just(U.WORD),
        st.integers(0, 0xFFFF),
    ),
)


@settings(max_examples=200)
@given(_addresses, st.booleans())
def test_format_parse_round_trip(addr: S5Address, english: bool) -> None:
    if addr.area.is_block and addr.unit is U.BYTE and addr.offset // 2 > 99999:
        return
    assert parse_s5_address(addr.to_str(english=english)) == addr
