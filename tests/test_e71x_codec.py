"""E71 commands beyond 00H-09H (issue 3): golden vectors both ways, binary and ASCII; properties.

Vectors marked "§12 #n" are the spec's golden vectors; the others are derived with the rules of
§3/§7 (no published example exists) and say so.
"""

from __future__ import annotations

import contextlib
import itertools
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import (
    Ack,
    BadRequest,
    Code,
    E71ClientConnection,
    E71ServerConnection,
    ErrorResponse,
    ExtensionRequest,
    OpaqueRequest,
    WordsResponse,
)
from plcstack.codecs.e71_commands import (
    CPU_MODELS,
    DECODERS,
    BytesResponse,
    CpuModelResponse,
    FixedBufferData,
    Loopback,
    LoopbackResponse,
    MonitorExt,
    OpaqueCommand,
    OpaqueResponse,
    RandomBufferResponse,
    ReadCpuModel,
    ReadExtDirect,
    ReadExtFile,
    ReadRandomBuffer,
    ReadSpecial,
    RegisterMonitorExt,
    RemoteRun,
    RemoteStop,
    TestExtFile,
    WriteExtDirect,
    WriteExtFile,
    WriteRandomBuffer,
    WriteSpecial,
    cpu_model_name,
)
from plcstack.codecs.e71_programs import build, parse_request, parse_response
from plcstack.errors import LocalProtocolError, RemoteProtocolError

B, A = Code.BINARY, Code.ASCII


def hx(text: str) -> bytes:
    return bytes.fromhex(text)


# (id, request, binary request, ASCII request, E71-side response, client-side event,
#  binary response, ASCII response)
GOLDEN: list[tuple[str, ExtensionRequest, str, str, Any, Any, str, str]] = [
    (
        "§12#13 15H model A3N",
        ReadCpuModel(),
        "15 FF 0A 00",
        "15FF000A",
        CpuModelResponse(0xA3),
        CpuModelResponse(0xA3),
        "95 00 A3 00",
        "9500A300",
    ),
    (
        "§12#15 13H remote RUN",
        RemoteRun(),
        "13 FF 0A 00",
        "13FF000A",
        Ack(0x13),
        Ack(0x13),
        "93 00",
        "9300",
    ),
    (
        "§12#15 14H remote STOP",
        RemoteStop(),
        "14 FF 0A 00",
        "14FF000A",
        Ack(0x14),
        Ack(0x14),
        "94 00",
        "9400",
    ),
    (
        "§12#16 16H loopback",
        Loopback(hx("12 34 AB")),
        "16 FF 0A 00 03 12 34 AB",
        "16FF000A031234AB",
        LoopbackResponse(hx("12 34 AB")),
        LoopbackResponse(hx("12 34 AB")),
        "96 00 03 12 34 AB",
        "9600031234AB",
    ),
    (
        "§12#17 0EH special module read",
        ReadSpecial(0x13, 0x7F0, 4),
        "0E FF 0A 00 F0 07 00 04 13 00",
        "0EFF000A0007F0041300",
        BytesResponse(0x0E, hx("09 18 20 34")),
        BytesResponse(0x0E, hx("09 18 20 34")),
        "8E 00 09 18 20 34",
        "8E0009182034",
    ),
    (
        "§12#18 0FH special module write",
        WriteSpecial(0x13, 0x750, hx("01 23 45 67")),
        "0F FF 0A 00 50 07 00 04 13 00 01 23 45 67",
        "0FFF000A00075004130001234567",
        Ack(0x0F),
        Ack(0x0F),
        "8F 00",
        "8F00",
    ),
    (
        "§12#19 17H ext file read",
        ReadExtFile(2, 70, 3),
        "17 FF 0A 00 46 00 00 00 20 52 02 00 03 00",
        "17FF000A00025220000000460300",
        WordsResponse(0x17, (0x1234, 0x8765, 0x013F)),
        WordsResponse(0x17, (0x1234, 0x8765, 0x013F)),
        "97 00 34 12 65 87 3F 01",
        "970012348765013F",
    ),
    (
        "derived 18H ext file write",
        WriteExtFile(2, 70, (0x1234, 0x8765)),
        "18 FF 0A 00 46 00 00 00 20 52 02 00 02 00 34 12 65 87",
        "18FF000A000252200000004602001234" + "8765",
        Ack(0x18),
        Ack(0x18),
        "98 00",
        "9800",
    ),
    (
        "§12#20 19H ext file test",
        TestExtFile(((2, 26, 0x1234), (3, 19, 0x0109))),
        "19 FF 0A 00 02 00 1A 00 00 00 20 52 02 00 34 12 13 00 00 00 20 52 03 00 09 01",
        "19FF000A0200000252200000001A123400035220000000130109",
        Ack(0x19),
        Ack(0x19),
        "99 00",
        "9900",
    ),
    (
        "derived 1AH ext monitor registration",
        RegisterMonitorExt(((2, 26), (3, 19))),
        "1A FF 0A 00 02 00 1A 00 00 00 20 52 02 00 13 00 00 00 20 52 03 00",
        "1AFF000A0200000252200000001A00035220000000" + "13",
        Ack(0x1A),
        Ack(0x1A),
        "9A 00",
        "9A00",
    ),
    (
        "derived 1BH ext monitor",
        MonitorExt(2),
        "1B FF 0A 00",
        "1BFF000A",
        WordsResponse(0x1B, (0x1234, 0x0109)),
        WordsResponse(0x1B, (0x1234, 0x0109)),
        "9B 00 34 12 09 01",
        "9B0012340109",
    ),
    (
        "§12#21 3BH direct read",
        ReadExtDirect(70, 4),
        "3B FF 0A 00 46 00 00 00 20 52 04 00",
        "3BFF000A5220000000460400",
        WordsResponse(0x3B, (0x1234, 0x8765, 0x013F, 0x0020)),
        WordsResponse(0x3B, (0x1234, 0x8765, 0x013F, 0x0020)),
        "BB 00 34 12 65 87 3F 01 20 00",
        "BB0012348765013F0020",
    ),
    (
        "derived 3CH direct write (block 2 R0 = 8192)",
        WriteExtDirect(8192, (0xABCD,)),
        "3C FF 0A 00 00 20 00 00 20 52 01 00 CD AB",
        "3CFF000A52200000200001" + "00ABCD",
        Ack(0x3C),
        Ack(0x3C),
        "BC 00",
        "BC00",
    ),
    (
        "§12#26 62H RAB write",
        WriteRandomBuffer(0, (0x1234, 0x5678, 0x9ABC)),
        "62 00 00 00 03 00 34 12 78 56 BC 9A",
        "620000000003123456789ABC",
        RandomBufferResponse(0x62),
        Ack(0x62),
        "E2 00",
        "E200",
    ),
    (
        "§12#26 61H RAB read",
        ReadRandomBuffer(0, 3),
        "61 00 00 00 03 00",
        "610000000003",
        RandomBufferResponse(0x61, 0, (0x1234, 0x5678, 0x9ABC)),
        WordsResponse(0x61, (0x1234, 0x5678, 0x9ABC)),
        "E1 00 34 12 78 56 BC 9A",
        "E100123456789ABC",
    ),
    (
        "§12#28 60H fixed buffer",
        FixedBufferData((1, 2, 3)),
        "60 00 03 00 01 00 02 00 03 00",
        "60000003000100020003",
        Ack(0x60),
        Ack(0x60),
        "E0 00",
        "E000",
    ),
    (
        "§12#14 12H parameter analysis (opaque)",
        OpaqueCommand(0x12),
        "12 FF 0A 00",
        "12FF000A",
        Ack(0x12),
        OpaqueResponse(0x12, b""),
        "92 00",
        "9200",
    ),
    (
        "5BH after 0EH: no special module (§7.5)",
        ReadSpecial(0x05, 0, 2),
        "0E FF 0A 00 00 00 00 02 05 00",
        "0EFF000A0000000205" + "00",
        ErrorResponse(0x0E, 0x5B, 0x12),
        ErrorResponse(0x0E, 0x5B, 0x12),
        "8E 5B 12 00",
        "8E5B1200",
    ),
    (
        "55H after 3CH",
        WriteExtDirect(0, (1,)),
        "3C FF 0A 00 00 00 00 00 20 52 01 00 01 00",
        "3CFF000A5220000000000100" + "0001",
        ErrorResponse(0x3C, 0x55),
        ErrorResponse(0x3C, 0x55),
        "BC 55",
        "BC55",
    ),
]


def _wire(code: Code, binary: str, ascii_: str) -> bytes:
    return hx(binary) if code is B else ascii_.encode()


CASES = [
    pytest.param(code, *case[1:], id=f"{case[0]} {code.value}")
    for case in GOLDEN
    for code in (B, A)
]


@pytest.mark.parametrize(("code", "req", "bq", "aq", "server", "client", "br", "ar"), CASES)
def test_golden_client_side(
    code: Code, req: ExtensionRequest, bq: str, aq: str, server: Any, client: Any, br: str, ar: str
) -> None:
    conn = E71ClientConnection(code)
    assert conn.send(req) == _wire(code, bq, aq)
    response = _wire(code, br, ar)
    events = []
    for i in range(len(response)):  # byte by byte: framing by the length rules
        conn.receive_data(response[i : i + 1])
        while (event := conn.next_event()) is not NEED_DATA:
            events.append(event)
    assert events == [client]
    assert conn.pending == 0


@pytest.mark.parametrize(("code", "req", "bq", "aq", "server", "client", "br", "ar"), CASES)
def test_golden_e71_side(
    code: Code, req: ExtensionRequest, bq: str, aq: str, server: Any, client: Any, br: str, ar: str
) -> None:
    conn = E71ServerConnection(code, extensions=DECODERS)
    conn.receive_data(_wire(code, bq, aq))
    event = conn.next_event()
    if isinstance(req, MonitorExt):
        assert isinstance(event, MonitorExt)  # the registered count is not on the wire
    else:
        assert event == req
    assert conn.next_event() is NEED_DATA
    assert conn.send(server) == _wire(code, br, ar)


@pytest.mark.parametrize(
    ("req", "binary", "ascii_", "server", "b_resp", "a_resp"),
    [
        (ReadRandomBuffer(0x1800, 1), "61 00 00 18 01 00", "610018000001", 0x51, "E1 51", "E151"),
        (ReadRandomBuffer(0x17FF, 2), "61 00 FF 17 02 00", "610017FF0002", 0x52, "E1 52", "E152"),
    ],
)
def test_golden_27_rab_errors(
    req: ReadRandomBuffer, binary: str, ascii_: str, server: int, b_resp: str, a_resp: str
) -> None:
    """§12 #27: requests the client refuses to send (so: E71 side, and the client decoding
    the same answers to a valid request)."""
    for code in (B, A):
        conn = E71ServerConnection(code, extensions=DECODERS)
        conn.receive_data(_wire(code, binary, ascii_))
        assert conn.next_event() == req
        answer = _wire(code, b_resp, a_resp)
        assert conn.send(RandomBufferResponse(0x61, server)) == answer
        client = E71ClientConnection(code)
        client.send(ReadRandomBuffer(0, 1))
        client.receive_data(answer)
        assert client.next_event() == ErrorResponse(0x61, server)


def test_without_extensions_the_core_stays_opaque() -> None:
    conn = E71ServerConnection(B)
    conn.receive_data(hx("15 FF 0A 00"))
    assert conn.next_event() == OpaqueRequest(0x15, hx("15 FF 0A 00"))


# -- §13 A2: the 6-character ASCII random access buffer response --------------------------------


@pytest.mark.parametrize(
    ("req", "server", "client", "text"),
    [
        (
            ReadRandomBuffer(0, 2, ascii_sub_chars=4),
            RandomBufferResponse(0x61, 0, (0x1234, 0x5678), ascii_sub_chars=4),
            WordsResponse(0x61, (0x1234, 0x5678)),
            "E1000012345678",
        ),
        (
            WriteRandomBuffer(0, (1,), ascii_sub_chars=4),
            RandomBufferResponse(0x62, 0, ascii_sub_chars=4),
            Ack(0x62),
            "E20000",
        ),
        (
            ReadRandomBuffer(6000, 200, ascii_sub_chars=4),
            RandomBufferResponse(0x61, 0x52, ascii_sub_chars=4),
            ErrorResponse(0x61, 0x52),
            "E10052",
        ),
    ],
)
def test_rab_ascii_six_char_form(req: Any, server: Any, client: Any, text: str) -> None:
    srv = E71ServerConnection(A, extensions=DECODERS)
    assert srv.send(server) == text.encode()
    conn = E71ClientConnection(A)
    if isinstance(req, ReadRandomBuffer) and req.count == 200:
        req = ReadRandomBuffer(6000, 100, ascii_sub_chars=4)
    conn.send(req)
    conn.receive_data(text.encode())
    assert conn.next_event() == client


def test_rab_binary_ignores_the_ascii_width_option() -> None:
    conn = E71ClientConnection(B)
    conn.send(ReadRandomBuffer(0, 1, ascii_sub_chars=4))
    conn.receive_data(hx("E1 00 34 12"))
    assert conn.next_event() == WordsResponse(0x61, (0x1234,))


# -- client-side limits: LocalProtocolError, nothing encoded -------------------------------------


@pytest.mark.parametrize(
    ("code", "req"),
    [
        (B, ReadRandomBuffer(0, 1018)),
        (A, ReadRandomBuffer(0, 509)),
        (B, ReadRandomBuffer(6144, 1)),
        (B, ReadRandomBuffer(6143, 2)),
        (B, WriteRandomBuffer(0, ())),
        (B, WriteRandomBuffer(0, (0x10000,))),
        (B, ReadSpecial(1, 0, 0)),
        (B, ReadSpecial(1, 0x1000000, 1)),
        (B, ReadSpecial(0x100, 0, 1)),
        (B, WriteSpecial(1, 0, b"")),
        (B, Loopback(b"")),
        (B, Loopback(bytes(257))),
        (B, ReadExtFile(1, 0, 257)),
        (B, ReadExtFile(0x10000, 0, 1)),
        (B, TestExtFile(tuple((1, i, 0) for i in range(41)))),
        (B, RegisterMonitorExt(tuple((1, i) for i in range(21)))),
        (B, MonitorExt(0)),
        (B, WriteExtDirect(0, ())),
        (A, FixedBufferData(tuple(range(509)))),
        (B, FixedBufferData(tuple(range(1018)))),
        (B, OpaqueCommand(0x15)),
        (B, RemoteRun(pc=0x100)),
        (B, RemoteRun(timer=-1)),
    ],
)
def test_client_refuses_bad_requests(code: Code, req: ExtensionRequest) -> None:
    conn = E71ClientConnection(code)
    with pytest.raises(LocalProtocolError):
        conn.send(req)
    assert conn.pending == 0


# -- response validation ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("req", "response"),
    [
        (ReadCpuModel(), "93 00 A3 00"),  # wrong subheader
        (ReadRandomBuffer(0, 1), "E2 00"),
        (FixedBufferData((1,)), "E1 00"),
        (Loopback(b"\x01\x02"), "96 00 01 01 02"),  # echoed length differs
    ],
)
def test_wrong_responses_raise_remote_protocol_error(req: ExtensionRequest, response: str) -> None:
    conn = E71ClientConnection(B)
    conn.send(req)
    conn.receive_data(hx(response))
    with pytest.raises(RemoteProtocolError):
        while conn.next_event() is not NEED_DATA:
            pass
        raise AssertionError("no error")  # pragma: no cover


def test_5bh_trailer_is_skipped_before_the_next_response() -> None:
    conn = E71ClientConnection(B)
    conn.send(ReadSpecial(5, 0, 2))
    conn.send(ReadCpuModel())
    conn.receive_data(hx("8E 5B 12 00 95 00 94 00"))
    assert conn.next_event() == ErrorResponse(0x0E, 0x5B, 0x12)
    assert conn.next_event() == CpuModelResponse(0x94)


@pytest.mark.parametrize("datagram", ["8E 5B 12 00", "8E 5B 12"])
def test_5bh_over_udp_with_or_without_trailer(datagram: str) -> None:
    conn = E71ClientConnection(B, transport="udp")
    conn.send(ReadSpecial(5, 0, 2))
    conn.receive_data(hx(datagram))
    assert conn.next_event() == ErrorResponse(0x0E, 0x5B, 0x12)


@pytest.mark.parametrize("datagram", ["95 00 A3", "95 00 A3 00 00", "95"])
def test_udp_datagram_of_the_wrong_size(datagram: str) -> None:
    conn = E71ClientConnection(B, transport="udp")
    conn.send(ReadCpuModel())
    conn.receive_data(hx(datagram))
    with pytest.raises(RemoteProtocolError):
        conn.next_event()


# -- E71-side decoding errors: the end code a real E71 sends -------------------------------------


@pytest.mark.parametrize(
    ("code", "frame", "end_code", "pc"),
    [
        (B, "17 FF 0A 00 46 00 00 00 20 44 02 00 03 00", 0x56, 0xFF),  # D is not R
        (B, "3B 05 0A 00 46 00 00 00 20 58 04 00", 0x56, 0x05),
        (A, "17FF000A0002522000000046030G", 0x54, 0xFF),  # non-hex count
        (A, "0FFF000A0007F0X41300", 0x54, None),  # non-hex count: cannot be sized
        (B, "17 FF 0A 00 46 00 00 00 20 52 02 00 03 02", 0x57, 0xFF),  # count field 0203H
    ],
)
def test_e71_side_bad_requests(code: Code, frame: str, end_code: int, pc: int | None) -> None:
    conn = E71ServerConnection(code, extensions=DECODERS)
    conn.receive_data(hx(frame) if code is B else frame.encode())
    event = conn.next_event()
    assert isinstance(event, BadRequest)
    assert (event.end_code, event.pc) == (end_code, pc)


# -- CPU model table -------------------------------------------------------------------------


def test_cpu_model_names() -> None:
    assert cpu_model_name(0xA3) == "A3, A3N"
    assert "A1S" in cpu_model_name(0x98)
    assert cpu_model_name(0x94).startswith("A3A")
    assert cpu_model_name(0x42) == "unknown model code 42H"
    assert len(CPU_MODELS) == 10


# -- experimental [R] program layout --------------------------------------------------------


@pytest.mark.parametrize(
    ("command", "address", "arg", "binary", "ascii_"),
    [
        (0x10, 0x123, 4, "10 FF 0A 00 23 01 00 04 00", "10FF000A0001230400"),
        (0x11, 0, b"\x01\x02", "11 FF 0A 00 00 00 00 02 00 01 02", "11FF000A00000002000102"),
        (0x0A, 0xFE05, 1, "0A FF 0A 00 05 FE 01 00", "0AFF000AFE050100"),
        (0x0C, 0x10, [0x1234], "0C FF 0A 00 10 00 01 00 34 12", "0CFF000A001001001234"),
        (0x1C, 0x100, 256, "1C FF 0A 00 00 01 00 00", "1CFF000A01000000"),
        (0x21, 2, b"\xab", "21 FF 0A 00 02 00 01 00 AB", "21FF000A00020100AB"),
    ],
)
def test_program_layout_r(command: int, address: int, arg: Any, binary: str, ascii_: str) -> None:
    for code, wire in ((B, hx(binary)), (A, ascii_.encode())):
        req = build(command, address, arg, code)
        frame = E71ClientConnection(code).send(req)
        assert frame == wire
        srv = E71ServerConnection(code, extensions=DECODERS)
        srv.receive_data(frame)  # the core's §11.1 length rules frame it
        event = srv.next_event()
        assert event == req
        assert isinstance(event, OpaqueCommand)
        access = parse_request(event, code)
        assert access.address == address
        if isinstance(arg, int):
            assert access.count == arg and access.data is None
        else:
            assert access.data == tuple(arg)


# Derived [R] golden vectors for every opaque command of §7.1 (request and answer, both codes):
# (command, address, count or data, binary request, ASCII request, values, binary answer,
#  ASCII answer). Reads answer words (0AH/0BH) or bytes; writes answer "cmd|80H 00".
OPAQUE_GOLDEN: list[tuple[int, int, Any, str, str, tuple[int, ...], str, str]] = [
    (
        0x0A,
        0,
        2,
        "0A FF 0A 00 00 00 02 00",
        "0AFF000A00000200",
        (0x1234, 0x5678),
        "8A 00 34 12 78 56",
        "8A0012345678",
    ),
    (
        0x0B,
        0xFF00,
        1,
        "0B FF 0A 00 00 FF 01 00",
        "0BFF000AFF000100",
        (0x8002,),
        "8B 00 02 80",
        "8B008002",
    ),
    (
        0x0C,
        5,
        [0xABCD],
        "0C FF 0A 00 05 00 01 00 CD AB",
        "0CFF000A00050100ABCD",
        (),
        "8C 00",
        "8C00",
    ),
    (0x0D, 5, [1], "0D FF 0A 00 05 00 01 00 01 00", "0DFF000A000501000001", (), "8D 00", "8D00"),
    (
        0x10,
        0xBFE,
        2,
        "10 FF 0A 00 FE 0B 00 02 00",
        "10FF000A000BFE0200",
        (0x12, 0xAB),
        "90 00 12 AB",
        "900012AB",
    ),
    (0x11, 0, [0xFF], "11 FF 0A 00 00 00 00 01 00 FF", "11FF000A0000000100FF", (), "91 00", "9100"),
    (
        0x1C,
        0x10,
        3,
        "1C FF 0A 00 10 00 03 00",
        "1CFF000A00100300",
        (0x41, 0x42, 0x43),
        "9C 00 41 42 43",
        "9C00414243",
    ),
    (0x1D, 0x10, [0x41], "1D FF 0A 00 10 00 01 00 41", "1DFF000A0010010041", (), "9D 00", "9D00"),
    (
        0x1E,
        0xE7FE,
        2,
        "1E FF 0A 00 FE E7 02 00",
        "1EFF000AE7FE0200",
        (1, 2),
        "9E 00 01 02",
        "9E000102",
    ),
    (0x1F, 0, 1, "1F FF 0A 00 00 00 01 00", "1FFF000A00000100", (9,), "9F 00 09", "9F0009"),
    (0x20, 0, [1, 2], "20 FF 0A 00 00 00 02 00 01 02", "20FF000A000002000102", (), "A0 00", "A000"),
    (0x21, 0, [3], "21 FF 0A 00 00 00 01 00 03", "21FF000A0000010003", (), "A1 00", "A100"),
    (0x39, 0x100, 1, "39 FF 0A 00 00 01 01 00", "39FF000A01000100", (0x7A,), "B9 00 7A", "B9007A"),
    (0x3A, 0x100, [0x7A], "3A FF 0A 00 00 01 01 00 7A", "3AFF000A010001007A", (), "BA 00", "BA00"),
]


@pytest.mark.parametrize(
    ("command", "address", "arg", "bq", "aq", "values", "br", "ar"),
    OPAQUE_GOLDEN,
    ids=[f"{c[0]:02X}H" for c in OPAQUE_GOLDEN],
)
@pytest.mark.parametrize("code", [B, A], ids=["binary", "ascii"])
def test_golden_opaque_commands_both_ways(
    code: Code,
    command: int,
    address: int,
    arg: Any,
    bq: str,
    aq: str,
    values: tuple[int, ...],
    br: str,
    ar: str,
) -> None:
    from plcstack.codecs.e71_programs import encode_answer

    request_wire, answer_wire = _wire(code, bq, aq), _wire(code, br, ar)
    req = build(command, address, arg, code)
    client = E71ClientConnection(code)
    assert client.send(req) == request_wire
    server = E71ServerConnection(code, extensions=DECODERS)
    server.receive_data(request_wire)
    event = server.next_event()
    assert event == req
    answer = encode_answer(command, values, code) if values else Ack(command)
    assert server.send(answer) == answer_wire
    client.receive_data(answer_wire)
    got = client.next_event()
    assert isinstance(got, OpaqueResponse)
    assert parse_response(req, got, code) == values


def test_every_command_of_table_7_1_has_golden_vectors() -> None:
    table_7_1 = {*range(0x00, 0x22), 0x39, 0x3A, 0x3B, 0x3C}
    core = set(range(0x00, 0x0A))  # tests/test_e71_codec.py
    here = {case[1].COMMAND for case in GOLDEN} | {c[0] for c in OPAQUE_GOLDEN}
    assert table_7_1 - core - here == set()
    assert {0x60, 0x61, 0x62} <= here


def test_program_read_response_r() -> None:
    for code, data in ((B, hx("34 12 78 56")), (A, b"12345678")):
        req = build(0x0A, 0, 2, code)
        conn = E71ClientConnection(code)
        conn.send(req)
        conn.receive_data((hx("8A 00") if code is B else b"8A00") + data)
        event = conn.next_event()
        assert isinstance(event, OpaqueResponse)
        assert parse_response(req, event, code) == (0x1234, 0x5678)


@pytest.mark.parametrize(
    ("command", "address", "arg"),
    [(0x12, 0, 1), (0x10, 1 << 24, 1), (0x1C, 0, 0), (0x1C, 0, 257), (0x1D, 0, 3), (0x1C, 0, b"x")],
)
def test_program_layout_refuses(command: int, address: int, arg: Any) -> None:
    with pytest.raises(LocalProtocolError):
        build(command, address, arg, B)


# -- properties ------------------------------------------------------------------------------

words = st.integers(0, 0xFFFF)
R_NUM = st.integers(0, 8191)
BLOCK = st.integers(1, 256)
requests = st.one_of(
    st.builds(RemoteRun),
    st.builds(RemoteStop),
    st.builds(ReadCpuModel, pc=st.integers(0, 0xFF), timer=st.integers(0, 0xFFFF)),
    st.builds(Loopback, st.binary(min_size=1, max_size=256)),
    st.builds(ReadSpecial, st.integers(0, 255), st.integers(0, 0xFFFFFF), st.integers(1, 256)),
    st.builds(
        WriteSpecial,
        st.integers(0, 255),
        st.integers(0, 0xFFFFFF),
        st.binary(min_size=1, max_size=256),
    ),
    st.builds(ReadExtFile, BLOCK, R_NUM, st.integers(1, 256)),
    st.builds(WriteExtFile, BLOCK, R_NUM, st.lists(words, min_size=1, max_size=256).map(tuple)),
    st.builds(
        TestExtFile, st.lists(st.tuples(BLOCK, R_NUM, words), min_size=1, max_size=40).map(tuple)
    ),
    st.builds(
        RegisterMonitorExt, st.lists(st.tuples(BLOCK, R_NUM), min_size=1, max_size=20).map(tuple)
    ),
    st.builds(ReadExtDirect, st.integers(0, 256 * 8192 - 1), st.integers(1, 256)),
    st.builds(
        WriteExtDirect,
        st.integers(0, 0xFFFFFFFF),
        st.lists(words, min_size=1, max_size=256).map(tuple),
    ),
    st.builds(ReadRandomBuffer, st.integers(0, 5000), st.integers(1, 508)),
    st.builds(
        WriteRandomBuffer,
        st.integers(0, 5000),
        st.lists(words, min_size=1, max_size=508).map(tuple),
    ),
    st.builds(FixedBufferData, st.lists(words, min_size=1, max_size=508).map(tuple)),
    st.builds(
        lambda c, a, n: build(c, a, n, B),
        st.sampled_from([0x0A, 0x10, 0x1C, 0x1E]),
        st.integers(0, 0xFFFF),
        st.integers(1, 256),
    ),
)


@settings(max_examples=150, deadline=None)
@given(req=requests, code=st.sampled_from([B, A]), cuts=st.lists(st.integers(0, 4000), max_size=6))
def test_round_trip_any_split(req: ExtensionRequest, code: Code, cuts: list[int]) -> None:
    if isinstance(req, OpaqueCommand) and code is A:
        req = build(req.command, *_opaque_args(req), A)
    frame = E71ClientConnection(code).send(req)
    srv = E71ServerConnection(code, extensions=DECODERS)
    bounds = sorted({0, len(frame), *(c % (len(frame) + 1) for c in cuts)})
    events = []
    for lo, hi in itertools.pairwise(bounds):
        srv.receive_data(frame[lo:hi])
        while (ev := srv.next_event()) is not NEED_DATA:
            events.append(ev)
    assert events == [req]


def _opaque_args(req: OpaqueCommand) -> tuple[int, int]:
    access = parse_request(req, B)
    return access.address, access.count


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=64), code=st.sampled_from([B, A]), req=requests)
def test_random_response_bytes_raise_only_remote_protocol_error(
    data: bytes, code: Code, req: ExtensionRequest
) -> None:
    if isinstance(req, OpaqueCommand) and code is A:
        req = build(req.command, *_opaque_args(req), A)
    for transport in ("tcp", "udp"):
        conn = E71ClientConnection(code, transport=transport)
        conn.send(req)
        conn.receive_data(data)
        with contextlib.suppress(RemoteProtocolError):
            conn.next_event()


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=64), code=st.sampled_from([B, A]))
def test_random_request_bytes_never_raise_on_the_e71_side(data: bytes, code: Code) -> None:
    for transport in ("tcp", "udp"):
        srv = E71ServerConnection(code, transport=transport, extensions=DECODERS)
        srv.receive_data(data)
        for _ in range(len(data) + 1):
            if srv.next_event() is NEED_DATA:
                break


# -- the simulator answers every extension request with a response the client can decode ---------


@settings(max_examples=150, deadline=None)
@given(
    req=requests,
    code=st.sampled_from([B, A]),
    state=st.sampled_from(["RUN", "STOP", "PAUSE"]),
    write_in_run=st.booleans(),
    group=st.sampled_from(["I", "IV", "V", "VII"]),
)
def test_simulator_answers_are_decodable(
    req: ExtensionRequest, code: Code, state: str, write_in_run: bool, group: str
) -> None:
    from plcstack.sim.e71 import execute
    from plcstack.sim.melsec_memory import CpuState, MelsecMemory

    if isinstance(req, OpaqueCommand) and code is A:
        req = build(req.command, *_opaque_args(req), A)
    mem = MelsecMemory(group, state=CpuState(state), write_in_run=write_in_run)
    server = E71ServerConnection(code, extensions=DECODERS)
    client = E71ClientConnection(code)
    server.receive_data(client.send(req))
    event = server.next_event()
    assert event == req
    answer = server.send(execute(mem, event, code))
    client.receive_data(answer)
    got = client.next_event()
    assert got is not NEED_DATA
    assert getattr(got, "command", req.COMMAND) == req.COMMAND
    assert client.pending == 0


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=120), code=st.sampled_from([B, A]))
def test_simulator_answers_garbage_with_extensions(data: bytes, code: Code) -> None:
    from plcstack.sim.e71 import execute
    from plcstack.sim.melsec_memory import MelsecMemory

    mem = MelsecMemory()
    server = E71ServerConnection(code, extensions=DECODERS)
    server.receive_data(data)
    for _ in range(len(data) + 1):
        event = server.next_event()
        if event is NEED_DATA:
            break
        assert server.send(execute(mem, event, code))
