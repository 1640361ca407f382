"""FETCH/WRITE 16-byte header codec: goldens of spec C.10 both ways, both framings, properties."""

from __future__ import annotations

import contextlib
import itertools
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.codecs import NEED_DATA
from plcstack.codecs.fetchwrite import (
    ERROR_MEANINGS,
    BadRequest,
    ClientConnection,
    FetchRequest,
    FetchResponse,
    Framing,
    Org,
    ServerConnection,
    WriteRequest,
    WriteResponse,
    data_bytes,
    encode_ack,
    encode_request,
    error_meaning,
    unit_size,
)
from plcstack.codecs.mk import MkConnection
from plcstack.errors import LocalProtocolError, RemoteProtocolError

H = bytes.fromhex
DATA_40 = b"".join((0x1000 + i).to_bytes(2, "big") for i in range(20))
ACK_OK_FETCH = H("53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00")
ACK_OK_WRITE = H("53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00")

# (name, request, request bytes, response, response bytes)
GOLDEN: list[tuple[str, Any, bytes, Any, bytes]] = [
    (
        "C.10-1 FETCH DB10 DW5 20 words",
        FetchRequest(Org.DB, 10, 5, 20),
        H("53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02"),
        FetchResponse(0, DATA_40),
        ACK_OK_FETCH + DATA_40,
    ),
    (
        "C.10-2 WRITE 4 bytes to MB100",
        WriteRequest(Org.MB, 0, 100, 4, H("DE AD BE EF")),
        H("53 35 10 01 03 03 03 08 02 00 00 64 00 04 FF 02 DE AD BE EF"),
        WriteResponse(0),
        ACK_OK_WRITE,
    ),
    (
        "C.10-3 FETCH missing DB99 -> error 02",
        FetchRequest(Org.DB, 99, 0, 1),
        H("53 35 10 01 03 05 03 08 01 63 00 00 00 01 FF 02"),
        FetchResponse(2),
        H("53 35 10 01 03 06 0F 03 02 FF 07 00 00 00 00 00"),
    ),
    (
        "C.10-4 WRITE DB10 DW5..DW6",
        WriteRequest(Org.DB, 10, 5, 2, H("12 34 10 03")),
        H("53 35 10 01 03 03 03 08 01 0A 00 05 00 02 FF 02 12 34 10 03"),
        WriteResponse(0),
        ACK_OK_WRITE,
    ),
]
IDS = [g[0] for g in GOLDEN]


def drain(conn: ClientConnection | ServerConnection) -> list[Any]:
    out: list[Any] = []
    while (ev := conn.next_event()) is not NEED_DATA:
        out.append(ev)
        if isinstance(conn, ServerConnection):
            break  # the server pauses until the request is answered
    return out


@pytest.mark.parametrize(("name", "req", "req_bytes", "resp", "resp_bytes"), GOLDEN, ids=IDS)
def test_golden_raw_client(
    name: str, req: Any, req_bytes: bytes, resp: Any, resp_bytes: bytes
) -> None:
    client = ClientConnection()
    assert client.send(req) == req_bytes
    client.receive_data(resp_bytes)
    assert client.next_event() == resp
    assert client.next_event() is NEED_DATA
    assert client.pending is None


@pytest.mark.parametrize(("name", "req", "req_bytes", "resp", "resp_bytes"), GOLDEN, ids=IDS)
def test_golden_raw_server(
    name: str, req: Any, req_bytes: bytes, resp: Any, resp_bytes: bytes
) -> None:
    server = ServerConnection()
    server.receive_data(req_bytes)
    assert server.next_event() == req
    assert server.send(resp) == resp_bytes
    assert server.next_event() is NEED_DATA


def test_golden_mk_both_directions() -> None:
    """C.10-5: FETCH then WRITE wrapped in MK, SeqNo 0 then 1 on each side, then a life ack."""
    pc_wire = [
        H("4D 4B 10 00 00 00 00 00") + GOLDEN[0][2],
        H("4D 4B 14 00 00 00 01 00") + GOLDEN[1][2],
    ]
    module_wire = [
        H("4D 4B 38 00 00 00 00 00") + ACK_OK_FETCH + DATA_40,
        H("4D 4B 10 00 00 00 01 00") + ACK_OK_WRITE,
    ]
    client = ClientConnection("mk")
    server = ServerConnection("mk", mk=MkConnection(strict=True))
    for i in range(2):
        _, req, _, resp, _ = GOLDEN[i]
        assert client.send(req) == pc_wire[i]
        server.receive_data(pc_wire[i])
        assert server.next_event() == req
        assert server.send(resp) == module_wire[i]
        client.receive_data(module_wire[i])
        assert client.next_event() == resp
    assert client.life_ack() == H("4D 4B 00 00 00 00 02 00")


def test_golden_mk_split_616_byte_write() -> None:
    """C.10-6: WRITE DB10 from DW0, 300 words, PC counter at 1 -> two telegrams; one 16-byte ack."""
    data = bytes((i * 7) & 0xFF for i in range(600))
    mk = MkConnection()
    mk.tx_seq = 1
    client = ClientConnection("mk", mk=mk)
    wire = client.send(WriteRequest.of(Org.DB, 10, 0, data))
    head = H("53 35 10 01 03 03 03 08 01 0A 00 00 01 2C FF 02")
    assert wire == (
        H("4D 4B 00 02 01 00 01 00") + head + data[:496] + H("4D 4B 68 00 00 00 02 00") + data[496:]
    )
    server = ServerConnection("mk")
    server.receive_data(wire)
    assert server.next_event() == WriteRequest(Org.DB, 10, 0, 300, data)
    ack = server.send(WriteResponse(0))
    assert ack == H("4D 4B 10 00 00 00 00 00") + ACK_OK_WRITE
    client.receive_data(ack)
    assert client.next_event() == WriteResponse(0)


def test_units_and_meanings() -> None:
    words = {Org.DB, Org.ZB, Org.TB, Org.BS, Org.AS, Org.DX, Org.DE}
    for org in Org:
        assert unit_size(org) == (2 if org in words else 1)
    assert data_bytes(Org.DB, 20) == 40 and data_bytes(Org.MB, 20) == 20
    with pytest.raises(LocalProtocolError):
        unit_size(0x0B)
    assert set(ERROR_MEANINGS) == {0, 1, 2, 3, 4, 0xFF}
    assert "does not exist" in error_meaning(2)
    assert "too small" in error_meaning(3)
    assert error_meaning(0x42) == "undocumented error code"


def test_fetch_byte_area_and_error_ack_without_data() -> None:
    client = ClientConnection()
    client.send(FetchRequest(Org.EB, 0, 3, 4))
    client.receive_data(ACK_OK_FETCH + b"\x01\x02")
    assert client.next_event() is NEED_DATA
    client.receive_data(b"\x03\x04")
    assert client.next_event() == FetchResponse(0, b"\x01\x02\x03\x04")
    client.send(FetchRequest(Org.DB, 10, 0, 100))
    client.receive_data(H("53 35 10 01 03 06 0F 03 03 FF 07 00 00 00 00 00"))
    assert client.next_event() == FetchResponse(3)


def test_free_bytes_of_the_ack_are_ignored() -> None:
    client = ClientConnection()
    client.send(WriteRequest.of(Org.MB, 0, 0, b"\x01"))
    client.receive_data(H("53 35 10 01 03 04 0F 03 00 FF 07 AA BB CC DD EE"))
    assert client.next_event() == WriteResponse(0)


@pytest.mark.parametrize(
    "ack",
    [
        H("53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00"),  # WRITE ack for a FETCH
        H("53 36 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00"),  # not "S5"
        H("53 35 10 01 03 06 0E 03 00 FF 07 00 00 00 00 00"),  # wrong ack block id
        H("53 35 10 01 03 06 0F 03 00 FF 02 00 00 00 00 00"),  # wrong empty block length
        H("53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02"),  # a request echoed back
    ],
)
def test_client_rejects_malformed_acks(ack: bytes) -> None:
    for framing in ("raw", "mk"):
        client = ClientConnection(framing)
        client.send(FetchRequest(Org.DB, 10, 5, 1))
        client.receive_data(ack if framing == "raw" else MkConnection().send_message(ack + b"ab"))
        with pytest.raises(RemoteProtocolError):
            client.next_event()


def test_client_mk_cross_checks_the_data_length() -> None:
    client = ClientConnection("mk")
    client.send(FetchRequest(Org.DB, 10, 5, 2))
    client.receive_data(MkConnection().send_message(ACK_OK_FETCH + b"\x00\x01\x00"))
    with pytest.raises(RemoteProtocolError, match="3 data bytes, the job needs 4"):
        client.next_event()
    client = ClientConnection("mk")
    client.send(FetchRequest(Org.DB, 10, 5, 2))
    err_with_data = H("53 35 10 01 03 06 0F 03 02 FF 07 00 00 00 00 00") + b"\x00\x01"
    client.receive_data(MkConnection().send_message(err_with_data))
    with pytest.raises(RemoteProtocolError):
        client.next_event()


def test_client_unsolicited_data() -> None:
    raw = ClientConnection()
    raw.receive_data(ACK_OK_WRITE)
    with pytest.raises(RemoteProtocolError, match="unsolicited"):
        raw.next_event()
    mk = ClientConnection("mk")
    tx = MkConnection()
    mk.receive_data(tx.life_ack())  # a life ack while idle is fine
    assert mk.next_event() is NEED_DATA
    mk.receive_data(tx.send_message(ACK_OK_WRITE))
    with pytest.raises(RemoteProtocolError, match="unsolicited"):
        mk.next_event()


def test_client_misuse() -> None:
    client = ClientConnection()
    client.send(FetchRequest(Org.MB, 0, 0, 1))
    with pytest.raises(LocalProtocolError, match="outstanding"):
        client.send(FetchRequest(Org.MB, 0, 0, 1))
    with pytest.raises(LocalProtocolError):
        ClientConnection().send(WriteRequest(Org.DB, 1, 0, 2, b"\x00\x01"))  # 2 words need 4 bytes
    with pytest.raises(LocalProtocolError):
        ClientConnection().send(FetchRequest(Org.DB, 256, 0, 1))
    with pytest.raises(LocalProtocolError):
        ClientConnection().send(FetchRequest(Org.DB, 1, 0x10000, 1))
    with pytest.raises(LocalProtocolError):
        WriteRequest.of(Org.DB, 1, 0, b"\x00")
    with pytest.raises(LocalProtocolError):
        ClientConnection().life_ack()
    with pytest.raises(LocalProtocolError):
        encode_ack(0x05, 0)
    with pytest.raises(LocalProtocolError):
        encode_ack(0x04, 0, b"data")


def test_server_bad_requests_raw() -> None:
    server = ServerConnection()
    # FETCH with unknown ORG 0x0B -> error 01, connection continues
    server.receive_data(H("53 35 10 01 03 05 03 08 0B 00 00 00 00 01 FF 02"))
    bad = server.next_event()
    assert isinstance(bad, BadRequest) and bad.error == 1 and not bad.close
    assert server.send(FetchResponse(1)) == H("53 35 10 01 03 06 0F 03 01 FF 07 00 00 00 00 00")
    # WRITE length 0 -> error 01, no data follows
    server.receive_data(H("53 35 10 01 03 03 03 08 02 00 00 00 00 00 FF 02"))
    bad = server.next_event()
    assert isinstance(bad, BadRequest) and bad.error == 1 and bad.reason == "length 0"
    server.send(WriteResponse(1))
    # WRITE with unknown ORG on a raw stream: answer, then close (data length unknown)
    server.receive_data(H("53 35 10 01 03 03 03 08 0B 00 00 00 00 01 FF 02 00 00"))
    bad = server.next_event()
    assert isinstance(bad, BadRequest) and bad.close


def test_server_bad_requests_mk() -> None:
    tx = MkConnection()
    server = ServerConnection("mk")
    # WRITE of 2 words carrying only 3 bytes -> error 01 [R] C.6.5
    server.receive_data(
        tx.send_message(H("53 35 10 01 03 03 03 08 01 0A 00 00 00 02 FF 02 01 02 03"))
    )
    bad = server.next_event()
    assert isinstance(bad, BadRequest) and bad.error == 1 and not bad.close
    server.send(WriteResponse(1))
    # unknown ORG in WRITE over MK: the message boundary is known, no need to close
    server.receive_data(tx.send_message(H("53 35 10 01 03 03 03 08 0B 00 00 00 00 01 FF 02 00 00")))
    bad = server.next_event()
    assert isinstance(bad, BadRequest) and not bad.close
    server.send(WriteResponse(1))
    server.receive_data(tx.send_message(b"S5\x10"))
    with pytest.raises(RemoteProtocolError):
        server.next_event()


@pytest.mark.parametrize(
    "header",
    [
        H("53 35 10 01 03 06 03 08 01 0A 00 05 00 14 FF 02"),  # opcode 06 in a request
        H("53 35 11 01 03 05 03 08 01 0A 00 05 00 14 FF 02"),  # header length 17
        H("53 35 10 01 03 05 03 07 01 0A 00 05 00 14 FF 02"),  # ORG block length 7
        H("00 00 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02"),  # no "S5"
        H("53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FE 02"),  # empty block id
    ],
)
def test_server_rejects_malformed_headers(header: bytes) -> None:
    server = ServerConnection()
    server.receive_data(header)
    with pytest.raises(RemoteProtocolError):
        server.next_event()


def test_server_misuse() -> None:
    server = ServerConnection()
    with pytest.raises(LocalProtocolError):
        server.send(WriteResponse(0))
    server.receive_data(GOLDEN[0][2])
    server.next_event()
    with pytest.raises(LocalProtocolError):
        server.send(WriteResponse(0))
    with pytest.raises(LocalProtocolError, match="40 data bytes"):
        server.send(FetchResponse(0, b"\x00\x00"))


# -- properties ----------------------------------------------------------------------------

ORGS = list(Org)


@st.composite
def jobs(draw: st.DrawFn) -> tuple[Any, Any]:
    org = draw(st.sampled_from(ORGS))
    db = draw(st.integers(0, 255))
    start = draw(st.integers(0, 0xFFFF))
    length = draw(st.integers(1, 400))
    size = unit_size(org) * length
    if draw(st.booleans()):
        req: Any = WriteRequest(
            org, db, start, length, draw(st.binary(min_size=size, max_size=size))
        )
        resp: Any = WriteResponse(draw(st.integers(0, 255)))
    else:
        req = FetchRequest(org, db, start, length)
        error = draw(st.sampled_from([0, 0, 1, 2, 3, 4, 0xFF, 0x42]))
        data = draw(st.binary(min_size=size, max_size=size)) if error == 0 else b""
        resp = FetchResponse(error, data)
    return req, resp


def chunked(wire: bytes, cuts: list[int]) -> list[bytes]:
    points = [0, *sorted(c % (len(wire) + 1) for c in cuts), len(wire)]
    return [wire[a:b] for a, b in itertools.pairwise(points)]


@settings(max_examples=150)
@given(
    st.lists(jobs(), min_size=1, max_size=4),
    st.sampled_from(["raw", "mk"]),
    st.lists(st.integers(0, 10_000), max_size=8),
)
def test_round_trip_any_split(
    cases: list[tuple[Any, Any]], framing: Framing, cuts: list[int]
) -> None:
    client = ClientConnection(framing)
    server = ServerConnection(framing, mk=MkConnection(strict=True))
    for req, resp in cases:
        wire = client.send(req)
        got: list[Any] = []
        for piece in chunked(wire, cuts):
            server.receive_data(piece)
            got += drain(server)
        assert got == [req]
        back = server.send(resp)
        answers: list[Any] = []
        for piece in chunked(back, cuts):
            client.receive_data(piece)
            answers += drain(client)
        assert answers == [resp]


@settings(max_examples=200)
@given(st.binary(max_size=200), st.sampled_from(["raw", "mk"]))
def test_random_bytes_server(data: bytes, framing: Framing) -> None:
    server = ServerConnection(framing)
    server.receive_data(data)
    try:
        for _ in range(20):
            ev = server.next_event()
            if ev is NEED_DATA:
                break
            if isinstance(ev, FetchRequest | BadRequest) and (
                not isinstance(ev, BadRequest) or ev.opcode == 0x05
            ):
                server.send(FetchResponse(1))
            else:
                server.send(WriteResponse(1))
    except RemoteProtocolError:
        pass


@settings(max_examples=200)
@given(st.binary(max_size=200), st.sampled_from(["raw", "mk"]), jobs())
def test_random_bytes_client(data: bytes, framing: Framing, job: tuple[Any, Any]) -> None:
    client = ClientConnection(framing)
    client.send(job[0])
    client.receive_data(data)
    with contextlib.suppress(RemoteProtocolError):
        drain(client)


@settings(max_examples=100)
@given(st.binary(max_size=60), jobs())
def test_random_bytes_after_valid_ack_prefix(tail: bytes, job: tuple[Any, Any]) -> None:
    client = ClientConnection()
    client.send(job[0])
    client.receive_data(ACK_OK_FETCH[:8] + tail)
    with contextlib.suppress(RemoteProtocolError):
        drain(client)


def test_encode_request_equals_server_view() -> None:
    req = FetchRequest(Org.TB, 0, 5, 3)
    assert encode_request(req)[8:14] == H("07 00 00 05 00 03")
