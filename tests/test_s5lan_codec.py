"""S5-LAN-LINK codec: goldens of spec A.10 both ways, validation order of A.7, properties."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.s5lan import (
    AREA_LETTERS,
    ERR_MEANINGS,
    HEADER_BYTE_ORDER,
    MAX_DATA_BYTES,
    BadRequest,
    ClientConnection,
    Header,
    Request,
    Response,
    ServerConnection,
    area_legal,
    byte_order_hint,
    err_meaning,
    estimate_seconds,
    response_timeout,
    swap_words,
)
from plcstack.errors import LocalProtocolError, RemoteProtocolError

H = bytes.fromhex

# -- goldens of A.10 --------------------------------------------------------------------------
A1_REQ = H("35 00 00 00 1A 52 57 44 0A 00 05 00 14 00 00 00 00 00 11 22 33 44 00 00 00 00")
A1_RSP = H("35 00 00 00 1A 52 57 44 0A 00 05 00 14 00 00 00 68 00 11 22 33 44 00 00 00 00")
A1_DATA = H(
    "00 10 01 10 02 10 03 10 04 10 05 10 06 10 07 10 08 10 09 10"
    "0A 10 0B 10 0C 10 0D 10 0E 10 0F 10 10 10 11 10 12 10 13 10"
)
A1_REQ_BIG = H("35 00 00 00 1A 52 57 44 00 0A 00 05 00 14 00 00 00 00 11 22 33 44 00 00 00 00")
A2_REQ = H(
    "35 00 00 00 1A 57 42 4D 00 00 64 00 04 00 00 00 00 00 00 00 00 00 00 00 00 00 DE AD BE EF"
)
A2_RSP = H("35 00 00 00 1A 57 42 4D 00 00 64 00 04 00 00 00 68 00 00 00 00 00 00 00 00 00")
A3_REQ = H("35 00 00 00 1A 52 57 44 63 00 00 00 01 00 00 00 00 00 00 00 00 00 00 00 00 00")
A3_RSP = H("35 00 00 00 1A 52 57 44 63 00 00 00 01 00 02 00 68 00 00 00 00 00 00 00 00 00")

UC = H("11 22 33 44")

GOLDENS = [
    # name, request event, request bytes, err, response data, response bytes
    (
        "A.10-1 read DB10 DW5 x20",
        Request.read("D", "W", 5, 20, db=10, user_code=UC),
        A1_REQ,
        0,
        A1_DATA,
        A1_RSP + A1_DATA,
    ),
    (
        "A.10-2 write MB100 DE AD BE EF",
        Request.write("M", "B", 100, H("DE AD BE EF")),
        A2_REQ,
        0,
        b"",
        A2_RSP,
    ),
    ("A.10-3 Err 2", Request.read("D", "W", 0, 1, db=99), A3_REQ, 2, b"", A3_RSP),
]


@pytest.mark.parametrize(("name", "req", "req_bytes", "err", "data", "rsp_bytes"), GOLDENS)
def test_golden_client_side(
    name: str, req: Request, req_bytes: bytes, err: int, data: bytes, rsp_bytes: bytes
) -> None:
    client = ClientConnection()
    assert client.send(req) == req_bytes
    assert client.next_event() is NEED_DATA
    client.receive_data(rsp_bytes)
    event = client.next_event()
    assert isinstance(event, Response)
    assert event.err == err
    assert event.data == data
    assert event.header.version == 104
    assert event.header.reserved == bytes(4)
    assert client.next_event() is NEED_DATA


@pytest.mark.parametrize(("name", "req", "req_bytes", "err", "data", "rsp_bytes"), GOLDENS)
def test_golden_server_side(
    name: str, req: Request, req_bytes: bytes, err: int, data: bytes, rsp_bytes: bytes
) -> None:
    server = ServerConnection()
    server.receive_data(req_bytes)
    event = server.next_event()
    assert event == req
    assert server.send_response(req.header, err, data) == rsp_bytes
    assert server.next_event() is NEED_DATA


def test_golden_words_low_byte_first() -> None:
    # DW5.. = 1000h + i travels low byte first; swap_words gives the S5 (big-endian) order back
    words = list(struct.unpack("<20H", A1_DATA))
    assert words == [0x1000 + i for i in range(20)]
    assert swap_words(A1_DATA) == struct.pack(">20H", *words)
    assert swap_words(swap_words(A1_DATA)) == A1_DATA
    with pytest.raises(ValueError):
        swap_words(b"\x01")


def test_header_byte_order_constant_and_big_endian_variant() -> None:
    assert HEADER_BYTE_ORDER == "little"
    req = Request.read("D", "W", 5, 20, db=10, user_code=UC)
    assert ClientConnection(header_byte_order="big").send(req) == A1_REQ_BIG
    assert Header.decode(A1_REQ_BIG, "big") == req.header
    with pytest.raises(LocalProtocolError):
        ClientConnection(header_byte_order="middle")  # type: ignore[arg-type]


def test_big_endian_peer_is_diagnosed_never_switched_to() -> None:
    # a big-endian module decodes our read of 1 flag byte as Count 256 and answers 256 bytes
    client = ClientConnection()
    req = Request.read("M", "B", 0, 1)
    wire = client.send(req)
    as_seen = Header.decode(wire, "big")
    assert as_seen.count == 256
    client.receive_data(as_seen.response().encode("big") + bytes(256))
    with pytest.raises(RemoteProtocolError, match="header_byte_order=big"):
        client.next_event()
    rsp = Header.decode(A1_RSP)
    assert byte_order_hint(rsp) == ""
    assert "byte-swapped" in byte_order_hint(Header.decode(rsp.response(2).encode("big")))
    assert "header_byte_order=little" in byte_order_hint(
        Header.decode(rsp.response(0).encode("little"), "big"), "big"
    )


# -- legality (A.4) and Err meanings (A.7) ----------------------------------------------------
@pytest.mark.parametrize("area", sorted(AREA_LETTERS))
@pytest.mark.parametrize("data_type", ["B", "W", "D", "b"])
def test_area_type_legality(area: str, data_type: str) -> None:
    expected = data_type == "W" or (data_type == "B" and area in "MAOEI")
    assert area_legal(area, data_type) is expected
    req = Request(Header("R", data_type, area, db=1, start=0, count=1))
    client = ClientConnection()
    server = ServerConnection()
    if expected:
        server.receive_data(client.send(req))
        assert server.next_event() == req
    else:
        with pytest.raises(LocalProtocolError):
            client.send(req)
        server.receive_data(req.header.encode())
        bad = server.next_event()
        assert isinstance(bad, BadRequest)
        assert bad.err == 6
        assert not bad.close


@pytest.mark.parametrize(
    ("err", "fragment"),
    [
        (0, "success"),
        (2, "does not exist"),
        (3, "too small"),
        (6, "incorrect request format"),
        (7, "max. 2048 bytes"),
        (9, "timeout in the communication"),
        (10, "too little data"),
        (1, "unknown error 1"),
        (-1, "unknown error -1"),
        (32767, "unknown error 32767"),
    ],
)
def test_err_meanings(err: int, fragment: str) -> None:
    assert fragment in err_meaning(err)
    assert set(ERR_MEANINGS) == {0, 2, 3, 6, 7, 9, 10}


def test_err_is_signed_on_the_wire() -> None:
    client = ClientConnection()
    client.send(Request.read("M", "B", 0, 1))
    client.receive_data(Header("R", "B", "M", count=1, err=-5).encode())
    event = client.next_event()
    assert isinstance(event, Response)
    assert event.err == -5
    assert event.meaning == "unknown error -5"


def test_timing_estimates() -> None:
    assert estimate_seconds(40) == pytest.approx(0.110)
    assert estimate_seconds(2048) == pytest.approx(3.122)
    assert response_timeout(0) == 2.0
    assert response_timeout(2048) == pytest.approx(7.244)


# -- client-side misuse and bad answers --------------------------------------------------------
@pytest.mark.parametrize(
    "req",
    [
        Request(Header("Q", "W", "D", 1, 0, 1)),
        Request(Header("R", "W", "D", 1, 0, 0)),
        Request(Header("R", "W", "D", 1, 0, 1025)),
        Request(Header("R", "B", "M", 0, 0, 2049)),
        Request(Header("R", "B", "T", 0, 0, 1)),
        Request(Header("R", "W", "Q", 0, 0, 1)),
        Request(Header("W", "W", "D", 1, 0, 2), b"\x00\x01"),
        Request(Header("R", "W", "D", 1, 0, 1), b"\x00\x01"),
        Request(Header("R", "W", "D", 70000, 0, 1)),
        Request(Header("R", "W", "D", 1, 0, 1, user_code=b"\x01")),
        Request(Header("R", "W", "\u20ac", 1, 0, 1)),
    ],
)
def test_client_refuses_bad_requests(req: Request) -> None:
    with pytest.raises(LocalProtocolError):
        ClientConnection().send(req)


def test_client_one_request_in_flight() -> None:
    client = ClientConnection()
    client.send(Request.read("M", "B", 0, 1))
    with pytest.raises(LocalProtocolError, match="one request at a time"):
        client.send(Request.read("M", "B", 0, 1))


@pytest.mark.parametrize(
    ("reply", "fragment"),
    [
        (Header("R", "W", "D", 10, 5, 21, user_code=UC).encode(), "count 21 instead of 20"),
        (Header("R", "W", "D", 10, 5, 20).encode(), "user_code"),
        (Header("R", "W", "D", 11, 5, 20, user_code=UC).encode(), "db 11"),
        (Header("W", "W", "D", 10, 5, 20, user_code=UC).encode(), "cmd"),
        (Header("R", "W", "D", 10, 5, 20, user_code=UC, hd_len=27).encode(), "HdLen 27"),
        (Header("R", "W", "D", 10, 5, 20, user_code=UC, plc_type=0x36).encode(), "PLCType"),
        (A1_RSP + A1_DATA + b"\x00", "more than the answer"),
    ],
)
def test_client_rejects_bad_answers(reply: bytes, fragment: str) -> None:
    client = ClientConnection()
    client.send(Request.read("D", "W", 5, 20, db=10, user_code=UC))
    client.receive_data(reply)
    with pytest.raises(RemoteProtocolError, match=fragment):
        client.next_event()
    with pytest.raises(LocalProtocolError):
        client.next_event()


def test_client_lenient_echo_and_unsolicited_bytes() -> None:
    client = ClientConnection(strict=False)
    client.send(Request.read("D", "W", 5, 20, db=10, user_code=UC))
    client.receive_data(Header("r", "W", "D", 10, 5, 20, user_code=UC).encode() + A1_DATA)
    event = client.next_event()
    assert isinstance(event, Response)
    assert event.echo_mismatch == ("cmd",)
    assert event.data == A1_DATA
    client.receive_data(b"\x35")
    with pytest.raises(RemoteProtocolError, match="no request pending"):
        client.next_event()


def test_lower_case_cmd_is_a_read_and_echoed() -> None:
    server = ServerConnection()
    server.receive_data(Header("r", "W", "D", 10, 5, 1).encode())
    event = server.next_event()
    assert isinstance(event, Request)
    assert event.header.is_read
    assert server.send_response(event.header, 0, b"\x00\x00")[5:6] == b"r"


# -- server validation order (A.7) -------------------------------------------------------------
def _server_events(data: bytes, server: ServerConnection | None = None) -> list[object]:
    server = server or ServerConnection()
    server.receive_data(data)
    events: list[object] = []
    while (event := server.next_event()) is not NEED_DATA:
        events.append(event)
    return events


@pytest.mark.parametrize(
    ("header", "data", "err", "close"),
    [
        (Header("R", "W", "D", 1, 0, 1, hd_len=20), b"", 6, True),
        (Header("R", "W", "D", 1, 0, 1, plc_type=0x36), b"", 6, True),
        (Header("?", "W", "D", 1, 0, 1), b"", 6, True),
        (Header("W", "Q", "D", 1, 0, 1), b"", 6, True),
        (Header("R", "Q", "D", 1, 0, 1), b"", 6, False),
        (Header("R", "W", "Y", 1, 0, 1), b"", 6, False),
        (Header("R", "w", "D", 1, 0, 1), b"", 6, False),
        (Header("R", "W", "d", 1, 0, 1), b"", 6, False),
        (Header("R", "W", "D", 1, 0, 0), b"", 6, False),
        (Header("W", "W", "D", 1, 0, 0), b"", 6, False),
        (Header("W", "B", "D", 1, 0, 2), b"\x01\x02", 6, False),
        (Header("R", "W", "D", 1, 0, 1025), b"", 7, False),
        (Header("R", "B", "M", 0, 0, 2049), b"", 7, False),
        (Header("W", "B", "M", 0, 0, 2049), bytes(2049), 7, False),
    ],
)
def test_server_rejects(header: Header, data: bytes, err: int, close: bool) -> None:
    server = ServerConnection()
    follow = Header("R", "B", "M", 0, 0, 1)
    events = _server_events(header.encode() + data + follow.encode(), server)
    bad = events[0]
    assert isinstance(bad, BadRequest)
    assert (bad.err, bad.close) == (err, close)
    if close:
        # framing is lost: nothing after it is parsed
        assert events == [bad]
    else:
        # the data of a rejected write were consumed, the next request parses cleanly
        assert events[1:] == [Request(follow)]
    assert server.send_response(bad.header, bad.err)[14:16] == struct.pack("<h", err)


def test_server_accepts_numeric_plc_type_unless_strict() -> None:
    header = Header("R", "W", "D", 1, 0, 1, plc_type=0x05)
    assert _server_events(header.encode()) == [Request(header)]
    bad = _server_events(header.encode(), ServerConnection(strict=True))[0]
    assert isinstance(bad, BadRequest)
    assert bad.close


def test_server_data_timeout_err_10_and_pending_error_kept() -> None:
    server = ServerConnection()
    assert not server.awaiting_data
    with pytest.raises(LocalProtocolError):
        server.data_timeout()
    assert _server_events(A2_REQ[:28], server) == []
    assert server.awaiting_data
    bad = server.data_timeout()
    assert (bad.err, bad.close) == (10, False)
    assert not server.awaiting_data
    assert _server_events(A1_REQ, server) == [Request(Header.decode(A1_REQ))]
    # a write already refused for its size keeps Err 7 when its data stop coming
    _server_events(Header("W", "B", "M", 0, 0, 3000).encode() + bytes(10), server)
    assert server.data_timeout().err == 7


def test_server_response_misuse() -> None:
    server = ServerConnection()
    read = Header("R", "W", "D", 1, 0, 2)
    with pytest.raises(LocalProtocolError):
        server.send_response(read, 0, b"\x00")
    with pytest.raises(LocalProtocolError):
        server.send_response(read, 2, b"\x00\x00")


# -- properties --------------------------------------------------------------------------------
@st.composite
def requests(draw: st.DrawFn) -> Request:
    area = draw(st.sampled_from(sorted(AREA_LETTERS)))
    data_type = "W" if area in "TZCDX" else draw(st.sampled_from("BW"))
    unit = 1 if data_type == "B" else 2
    count = draw(st.integers(1, MAX_DATA_BYTES // unit))
    cmd = draw(st.sampled_from("RrWw"))
    header = Header(
        cmd,
        data_type,
        area,
        db=draw(st.integers(0, 0xFFFF)),
        start=draw(st.integers(0, 0xFFFF)),
        count=count,
        user_code=draw(st.binary(min_size=4, max_size=4)),
    )
    data = draw(st.binary(min_size=count * unit, max_size=count * unit)) if cmd in "Ww" else b""
    return Request(header, data)


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    chunks, last = [], 0
    for p in [*points, len(data)]:
        chunks.append(data[last:p])
        last = p
    return chunks


@settings(max_examples=100, deadline=None)
@given(
    st.lists(requests(), min_size=1, max_size=3),
    st.lists(st.integers(0, 10_000), max_size=8),
    st.lists(st.sampled_from([0, 0, 2, 3, 6, 7, 9, 10, -1, 0x7FFF]), min_size=3, max_size=3),
)
def test_round_trip_and_split_invariance(
    reqs: list[Request], cuts: list[int], errs: list[int]
) -> None:
    server = ServerConnection()
    wire = b""
    for req in reqs:
        client = ClientConnection()
        wire += client.send(req)
    events: list[object] = []
    for chunk in _split(wire, cuts):
        server.receive_data(chunk)
        while (event := server.next_event()) is not NEED_DATA:
            events.append(event)
    assert events == reqs
    # and back: the answer, split anywhere, gives the client the same response
    for req, err in zip(reqs, errs, strict=False):
        client = ClientConnection()
        client.send(req)
        ok_read = req.header.is_read and err == 0
        data = bytes(range(256)) * 8 if ok_read else b""
        data = data[: req.header.data_len or 0]
        answer = server.send_response(req.header, err, data)
        got: list[object] = []
        for chunk in _split(answer, cuts):
            client.receive_data(chunk)
            while (event := client.next_event()) is not NEED_DATA:
                got.append(event)
        assert got == [Response(req.header.response(err), data)]


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), st.lists(st.integers(0, 400), max_size=6))
def test_server_survives_random_bytes(data: bytes, cuts: list[int]) -> None:
    server = ServerConnection()
    for chunk in _split(data, cuts):
        server.receive_data(chunk)
        while (event := server.next_event()) is not NEED_DATA:
            assert isinstance(event, Request | BadRequest)
            if isinstance(event, BadRequest):
                server.send_response(event.header, event.err)
            elif event.header.is_read:
                server.send_response(event.header, 0, bytes(event.header.data_len or 0))
        if server.awaiting_data:
            server.data_timeout()


@settings(max_examples=200, deadline=None)
@given(requests(), st.binary(max_size=200))
def test_client_random_answer_only_remote_protocol_error(req: Request, data: bytes) -> None:
    client = ClientConnection()
    client.send(req)
    client.receive_data(data)
    try:
        while isinstance(client.next_event(), Response):
            pass
    except RemoteProtocolError:
        assert len(data) >= 26
