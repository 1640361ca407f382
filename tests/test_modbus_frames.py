"""Modbus TCP frames (Sans-IO) and the register layouts of every tag type, without a network.

Golden frames follow the examples of the Modbus Application Protocol Specification V1.1b3
(section 6) wrapped in the MBAP header of the Messaging on TCP/IP Implementation Guide.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from plcstack.errors import RemoteProtocolError
from plcstack.north.modbus.frames import (
    ModbusServerConnection,
    Request,
    exception_frame,
    response_frame,
)
from plcstack.north.modbus.registers import layout_for
from plcstack.poll.config import TagConfig
from plcstack.values import WordOrder, value_type
from plcstack.values.points import Scale


def mbap(transaction: int, pdu: bytes, unit: int = 1) -> bytes:
    return struct.pack(">HHHB", transaction, 0, len(pdu) + 1, unit) + pdu


def decode(data: bytes) -> list[Request]:
    conn = ModbusServerConnection()
    conn.receive_data(data)
    out = []
    while (request := conn.next_request()) is not None:
        out.append(request)
    return out


def test_read_holding_registers_golden() -> None:
    # spec 6.3: read registers 108-110 (address 0x006B, 3 registers)
    (request,) = decode(mbap(0x0102, bytes.fromhex("03006B0003")))
    assert request == Request(0x0102, 1, 3, 0x6B, 3)
    answer = response_frame(request, [0x022B, 0x0000, 0x0064])
    assert answer == mbap(0x0102, bytes.fromhex("0306022B00000064"))


def test_read_coils_golden() -> None:
    # spec 6.1: coils 20-38 (address 0x0013, 19 coils) -> CD 6B 05
    (request,) = decode(mbap(7, bytes.fromhex("0100130013")))
    bits = [1, 0, 1, 1, 0, 0, 1, 1, 1, 1, 0, 1, 0, 1, 1, 0, 1, 0, 1]
    assert response_frame(request, bits) == mbap(7, bytes.fromhex("0103CD6B05"))


def test_write_requests_golden() -> None:
    coil, register, coils, registers = decode(
        mbap(1, bytes.fromhex("0500ACFF00"))
        + mbap(2, bytes.fromhex("0600010003"))
        + mbap(3, bytes.fromhex("0F0013000A02CD01"))
        + mbap(4, bytes.fromhex("100001000204000A0102"))
    )
    assert coil.values == (1,) and response_frame(coil) == mbap(1, bytes.fromhex("0500ACFF00"))
    assert register.values == (3,)
    assert response_frame(register) == mbap(2, bytes.fromhex("0600010003"))
    assert coils.values == (1, 0, 1, 1, 0, 0, 1, 1, 1, 0)
    assert response_frame(coils) == mbap(3, bytes.fromhex("0F0013000A"))
    assert registers.values == (0x000A, 0x0102)
    assert response_frame(registers) == mbap(4, bytes.fromhex("1000010002"))


@pytest.mark.parametrize(
    ("pdu", "code"),
    [
        ("07", 0x01),  # read exception status: not served
        ("2B0E0100", 0x01),  # device identification: not served
        ("0300000000", 0x03),  # count 0
        ("030000007E", 0x03),  # 126 registers
        ("01000007D1", 0x03),  # 2001 coils
        ("03FFFF0002", 0x02),  # past address 65535
        ("0500001234", 0x03),  # a coil is FF00 or 0000
        ("0F0000000A0101", 0x03),  # 10 coils need 2 bytes
        ("1000000002040001", 0x03),  # byte count says 4, 2 follow
        ("03000001", 0x03),  # too short
        ("030000000100", 0x03),  # too long
    ],
)
def test_bad_pdus_become_exception_answers(pdu: str, code: int) -> None:
    (request,) = decode(mbap(9, bytes.fromhex(pdu)))
    assert request.error == code
    function = bytes.fromhex(pdu)[0]
    assert exception_frame(request, code) == mbap(9, bytes((function | 0x80, code)))


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (struct.pack(">HHHB", 1, 1, 6, 1) + bytes(5), "protocol id 1"),
        (struct.pack(">HHHB", 1, 0, 1, 1), "length 1"),
        (struct.pack(">HHHB", 1, 0, 300, 1), "length 300"),
    ],
)
def test_broken_framing_is_a_remote_protocol_error(frame: bytes, message: str) -> None:
    with pytest.raises(RemoteProtocolError, match=message):
        decode(frame)


def test_any_split_of_the_stream_gives_the_same_requests() -> None:
    stream = mbap(1, bytes.fromhex("0300000002")) + mbap(2, bytes.fromhex("0600010003"))
    whole = decode(stream)
    for cut in range(len(stream) + 1):
        conn = ModbusServerConnection()
        got = []
        for part in (stream[:cut], stream[cut:]):
            conn.receive_data(part)
            while (request := conn.next_request()) is not None:
                got.append(request)
        assert got == whole


@given(st.binary(max_size=300))
def test_arbitrary_bytes_raise_only_remote_protocol_error(data: bytes) -> None:
    conn = ModbusServerConnection()
    conn.receive_data(data)
    try:
        while conn.next_request() is not None:
            pass
    except RemoteProtocolError:
        pass


def tag(type_name: str, count: int = 1, scale: Scale | None = None) -> TagConfig:
    return TagConfig("t", "D0", value_type(type_name), count, scale=scale)


@pytest.mark.parametrize(
    ("type_name", "value", "words"),
    [
        ("int16", -2, [0xFFFE]),
        ("uint16", 65535, [0xFFFF]),
        ("int8", -1, [0xFFFF]),
        ("kf", -32768, [0x8000]),
        ("bcd16", 1234, [1234]),
        ("kz", 999, [999]),
        ("int32", -100000, [0xFFFE, 0x7960]),
        ("uint32", 0x12345678, [0x1234, 0x5678]),
        ("bcd32", 12345678, [0x00BC, 0x614E]),
        ("float32", 21.5, [0x41AC, 0x0000]),
        ("kt", 1.5, [0x3FC0, 0x0000]),
        ("kg", -3.25, [0xC050, 0x0000]),
        ("string:3", "ABC", [0x4142, 0x4300]),
        ("kc", "OK", [0x4F4B]),
        ("ky", (12, 255), [0x0CFF]),
        ("bool", True, [1]),
    ],
)
def test_register_layouts_round_trip(type_name: str, value: object, words: list[int]) -> None:
    layout = layout_for(tag(type_name), 16, "hr", 0)
    assert layout.encode(value, WordOrder.BIG) == words
    assert layout.decode(words, WordOrder.BIG) == value
    if layout.kind in ("int32", "uint32", "float32"):  # text is not word-ordered
        assert layout.encode(value, WordOrder.LITTLE) == words[::-1]
        assert layout.decode(words[::-1], WordOrder.LITTLE) == value


def test_scaled_tags_are_float32_engineering_values_and_arrays_are_consecutive() -> None:
    scaled = layout_for(tag("int16", scale=Scale(0, 1000, 0.0, 100.0)), 16, "ir", 7)
    assert (scaled.kind, scaled.start, scaled.end) == ("float32", 7, 9)
    array = layout_for(tag("int32", count=3), 16, "hr", 10)
    assert array.end == 16
    assert array.encode([1, -1, 2], WordOrder.BIG) == [0, 1, 0xFFFF, 0xFFFF, 0, 2]


def test_a_raw_tag_takes_its_points_width() -> None:
    assert layout_for(tag("raw"), 1, "co", 0).kind == "bit"
    assert layout_for(tag("raw"), 16, "hr", 0).kind == "uint16"
    with pytest.raises(ValueError, match="coil holds one bit"):
        layout_for(tag("raw"), 16, "co", 0)
