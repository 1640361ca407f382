"""MK (Tani SPS-Header) framing: goldens of spec C.10-5/C.10-6, properties, sequence checks."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.codecs import NEED_DATA
from plcstack.codecs.mk import (
    LifeAck,
    LifeAckTimer,
    Message,
    MkConnection,
    encode_telegram,
)
from plcstack.errors import LocalProtocolError, RemoteProtocolError

H = bytes.fromhex

FETCH_REQ = H("53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02")
FETCH_ACK = H("53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00") + b"".join(
    (0x1000 + i).to_bytes(2, "big") for i in range(20)
)
WRITE_REQ = H("53 35 10 01 03 03 03 08 02 00 00 64 00 04 FF 02 DE AD BE EF")
WRITE_ACK = H("53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00")

# (message, sender's counter before, expected wire bytes): C.10-5
GOLDEN_SINGLE = [
    (FETCH_REQ, 0, H("4D 4B 10 00 00 00 00 00") + FETCH_REQ),
    (FETCH_ACK, 0, H("4D 4B 38 00 00 00 00 00") + FETCH_ACK),
    (WRITE_REQ, 1, H("4D 4B 14 00 00 00 01 00") + WRITE_REQ),
    (WRITE_ACK, 1, H("4D 4B 10 00 00 00 01 00") + WRITE_ACK),
]


def events(conn: MkConnection) -> list[Message | LifeAck]:
    out: list[Message | LifeAck] = []
    while (ev := conn.next_event()) is not NEED_DATA:
        out.append(ev)
    return out


@pytest.mark.parametrize(("message", "seq", "wire"), GOLDEN_SINGLE)
def test_golden_encode(message: bytes, seq: int, wire: bytes) -> None:
    conn = MkConnection()
    conn.tx_seq = seq
    assert conn.send_message(message) == wire
    assert conn.tx_seq == seq + 1


@pytest.mark.parametrize(("message", "seq", "wire"), GOLDEN_SINGLE)
def test_golden_decode(message: bytes, seq: int, wire: bytes) -> None:
    conn = MkConnection(strict=True)
    conn.receive_data(wire)
    assert events(conn) == [Message(message, seq, 1)]


def test_golden_sequence_of_two_jobs_then_life_ack() -> None:
    pc = MkConnection()
    assert pc.send_message(FETCH_REQ) == GOLDEN_SINGLE[0][2]
    assert pc.send_message(WRITE_REQ) == GOLDEN_SINGLE[2][2]
    # C.10-5: the life ack carries the current counter (2) and does not increment it
    assert pc.life_ack() == H("4D 4B 00 00 00 00 02 00")
    assert pc.life_ack() == H("4D 4B 00 00 00 00 02 00")
    assert pc.tx_seq == 2


def _write_300_words() -> bytes:
    header = H("53 35 10 01 03 03 03 08 01 0A 00 00 01 2C FF 02")
    return header + bytes(range(256)) * 2 + bytes(range(88))


def test_golden_split_616_byte_write() -> None:
    message = _write_300_words()
    assert len(message) == 616
    pc = MkConnection()
    pc.tx_seq = 1
    wire = pc.send_message(message)
    t1 = H("4D 4B 00 02 01 00 01 00") + message[:512]
    t2 = H("4D 4B 68 00 00 00 02 00") + message[512:]
    assert wire == t1 + t2
    assert wire[8:24] == H("53 35 10 01 03 03 03 08 01 0A 00 00 01 2C FF 02")
    module = MkConnection(strict=True)
    module.receive_data(wire)
    assert events(module) == [Message(message, 1, 2)]


def test_life_ack_between_continuation_telegrams_is_not_reassembled() -> None:
    message = _write_300_words()
    pc = MkConnection()
    wire = pc.send_message(message)
    t1, t2 = wire[: 8 + 512], wire[8 + 512 :]
    module = MkConnection(strict=True)
    module.receive_data(t1 + encode_telegram(b"", 7) + t2)
    assert events(module) == [LifeAck(7), Message(message, 0, 2)]
    assert module.life_acks_received == 1


def test_empty_message_is_refused() -> None:
    with pytest.raises(LocalProtocolError):
        MkConnection().send_message(b"")


def test_sequence_wraps() -> None:
    conn = MkConnection()
    conn.tx_seq = 0xFFFF
    wire = conn.send_message(b"ab") + conn.send_message(b"cd")
    assert wire[6:8] == b"\xff\xff" and wire[16:18] == b"\x00\x00"
    rx = MkConnection(strict=True)
    rx.receive_data(wire)
    assert events(rx) == [Message(b"ab", 0xFFFF), Message(b"cd", 0)]


@pytest.mark.parametrize("first", [0, 1, 500])
def test_strict_learns_the_base_from_the_first_telegram(first: int) -> None:
    rx = MkConnection(strict=True)
    rx.receive_data(encode_telegram(b"x", first) + encode_telegram(b"y", first + 1))
    assert [e.data for e in events(rx) if isinstance(e, Message)] == [b"x", b"y"]


def test_sequence_gap_fatal_by_default_and_only_counted_when_turned_off() -> None:
    """Issue 11 item 4: checked by default (a delayed copy repeats an earlier SeqNo);
    ``check_seq=False`` is the way off for CPs that do not count."""
    wire = encode_telegram(b"x", 0) + encode_telegram(b"", 9) + encode_telegram(b"y", 2)
    lenient = MkConnection(check_seq=False)
    lenient.receive_data(wire)
    assert len(events(lenient)) == 3
    assert lenient.sequence_mismatches == 1
    default = MkConnection()
    default.receive_data(wire)
    assert default.next_event() == Message(b"x", 0)
    assert default.next_event() == LifeAck(9)
    with pytest.raises(RemoteProtocolError, match="sequence number 2 where 1") as info:
        default.next_event()
    assert "mk_seq=0" in info.value.message
    strict = MkConnection(strict=True)
    strict.receive_data(wire)
    assert strict.next_event() == Message(b"x", 0)
    assert strict.next_event() == LifeAck(9)  # life acks are never checked
    with pytest.raises(RemoteProtocolError, match="sequence number 2 where 1"):
        strict.next_event()


def test_bad_magic_detected_early() -> None:
    rx = MkConnection()
    rx.receive_data(b"S5")
    with pytest.raises(RemoteProtocolError, match="framing"):
        rx.next_event()
    rx = MkConnection()
    rx.receive_data(b"X")
    with pytest.raises(RemoteProtocolError):
        rx.next_event()


def test_strict_limits() -> None:
    big = encode_telegram(bytes(1461), 0)
    MkConnection().receive_data(big)  # lenient accepts (D.C2)
    lenient = MkConnection()
    lenient.receive_data(big)
    assert lenient.next_event() == Message(bytes(1461))
    strict = MkConnection(strict=True)
    strict.receive_data(big)
    with pytest.raises(RemoteProtocolError, match="1460"):
        strict.next_event()
    flagged = H("4D 4B 01 00 02 00 00 00 41")
    lenient = MkConnection()
    lenient.receive_data(flagged)
    assert lenient.next_event() == Message(b"A")
    strict = MkConnection(strict=True)
    strict.receive_data(flagged)
    with pytest.raises(RemoteProtocolError, match="reserved"):
        strict.next_event()


def test_max_message_guard() -> None:
    rx = MkConnection(max_message=1000)
    rx.receive_data(encode_telegram(bytes(600), 0, more=True) + encode_telegram(bytes(600), 1))
    with pytest.raises(RemoteProtocolError, match="exceeds 1000"):
        events(rx)


def test_life_ack_timer() -> None:
    timer = LifeAckTimer(10.0, 30.0, now=100.0)
    assert timer.next_wakeup() == 110.0
    assert not timer.ack_due(109.9) and timer.ack_due(110.0)
    timer.sent(110.0)
    assert timer.next_wakeup() == 120.0
    assert not timer.dead(129.9) and timer.dead(130.0)
    timer.received(125.0)
    assert not timer.dead(130.0)
    off = LifeAckTimer(None, None, now=0.0)
    assert off.next_wakeup() is None and not off.ack_due(1e9) and not off.dead(1e9)


# -- properties ----------------------------------------------------------------------------

messages = st.lists(st.binary(min_size=1, max_size=1500), min_size=1, max_size=5)


@st.composite
def stream_and_cuts(draw: st.DrawFn) -> tuple[list[bytes], bytes, list[int]]:
    msgs = draw(messages)
    tx = MkConnection(max_send_data=draw(st.integers(1, 600)))
    tx.tx_seq = draw(st.integers(0, 0xFFFF))
    wire = b""
    for m in msgs:
        if draw(st.booleans()):
            wire += tx.life_ack()
        wire += tx.send_message(m)
    cuts = sorted(draw(st.lists(st.integers(0, len(wire)), max_size=12)))
    return msgs, wire, cuts


@settings(max_examples=150)
@given(stream_and_cuts())
def test_round_trip_and_split_invariance(case: tuple[list[bytes], bytes, list[int]]) -> None:
    msgs, wire, cuts = case
    rx = MkConnection(strict=False)
    got: list[bytes] = []
    prev = 0
    for cut in [*cuts, len(wire)]:
        rx.receive_data(wire[prev:cut])
        prev = cut
        got += [e.data for e in events(rx) if isinstance(e, Message)]
    assert got == msgs
    assert rx.sequence_mismatches == 0
    assert rx.buffered == 0


@settings(max_examples=200)
@given(st.binary(max_size=300))
def test_random_bytes_raise_only_remote_protocol_error(data: bytes) -> None:
    for strict in (False, True):
        rx = MkConnection(strict=strict, max_message=2000)
        rx.receive_data(data)
        with contextlib.suppress(RemoteProtocolError):
            events(rx)


@settings(max_examples=100)
@given(st.binary(max_size=120))
def test_random_bytes_after_magic_raise_only_remote_protocol_error(data: bytes) -> None:
    rx = MkConnection(strict=True, max_message=100)
    rx.receive_data(b"MK" + data)
    with contextlib.suppress(RemoteProtocolError):
        events(rx)
