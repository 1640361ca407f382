"""AS511 codec: the golden sequences of spec B.11 in both directions, and properties."""

from __future__ import annotations

import contextlib
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plcstack.codecs import as511
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import (
    AGConnection,
    AGState,
    Done,
    Idled,
    Job,
    Nak,
    PGConnection,
    PGState,
    Request,
    Response,
    Timeout,
    Unstuffer,
    stuff,
    unstuff,
)
from plcstack.errors import LocalProtocolError, RemoteProtocolError


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# (direction, bytes) with "PG" = PG->AG, "AG" = AG->PG, exactly as the tables of B.11.
_HEAD = [("PG", "02"), ("AG", "10 06"), ("PG", "{fn}"), ("AG", "02"), ("PG", "10 06")]
_HEAD += [("AG", "16 10 03"), ("PG", "10 06")]
_TAIL = [("AG", "02"), ("PG", "10 06"), ("AG", "12 10 03"), ("PG", "10 06")]


def seq(fn: str, params: str, data: str | None) -> list[tuple[str, bytes]]:
    steps = [(d, b.format(fn=fn)) for d, b in _HEAD]
    steps.append(("PG", params))
    steps.append(("AG", "10 06"))
    if data is not None:
        steps += [("AG", "02"), ("PG", "10 06"), ("AG", data), ("PG", "10 06")]
    steps += _TAIL
    return [(d, h(b)) for d, b in steps]


SYSPAR = (
    "00 00 00 00 00 EF 00 EF 80 EE 00 ED 00 EC 00 EA 00 00 00 7F FF 00 00 02 00 02 00 02 00 02"
    " 00 02 00 02 00 02 00 00 00 00 00 00 05 00 00 00 00 00 00 00 00 10 03"
)

# name -> (job, steps, expected unstuffed result)
GOLDENS = {
    "B.11.1 B_INFO DB5": (
        as511.b_info_job(1, 5),
        seq("1A", "01 05 10 04", "00 4A 10 10 70 70 41 05 00 00 00 00 00 15 10 03"),
        h("00 4A 10 70 70 41 05 00 00 00 00 00 15"),
    ),
    "B.11.2 DB_READ DB5 DW0..3": (
        as511.read_job(0x4A10, 8),
        seq("04", "4A 10 10 4A 17 10 04", "00 00 00 00 00 12 34 00 10 10 AB CD 10 10 10 10 10 03"),
        h("00 00 00 00 00 12 34 00 10 AB CD 10 10"),
    ),
    "B.11.3 DB_WRITE DB5 DW2..3": (
        as511.write_job(0x4A14, h("01 02 10 03")),
        seq("03", "4A 14 01 02 10 10 03 10 04", None),
        b"",
    ),
    "B.11.4 system parameters": (
        as511.system_parameters_job(),
        seq("18", "10 04", SYSPAR),
        unstuff(h(SYSPAR)),
    ),
    "B.11.4 read MB0..3": (
        as511.read_job(0xEE00, 4),
        seq("04", "EE 00 EE 03 10 04", "00 00 00 00 00 01 02 03 04 10 03"),
        h("00 00 00 00 00 01 02 03 04"),
    ),
    "B.11.4 stop": (as511.stop_job(0xEA00), seq("03", "EA 0C 88 04 10 04", None), b""),
    "B.11.4 start": (as511.run_job(0xEA00), seq("03", "EA 0C 68 00 10 04", None), b""),
}

STREAMS = {
    # the "PG stream" / "AG stream" lines of B.11, verbatim
    "B.11.1 B_INFO DB5": (
        "02 1A 10 06 10 06 01 05 10 04 10 06 10 06 10 06 10 06",
        "10 06 02 16 10 03 10 06 02 00 4A 10 10 70 70 41 05 00 00 00 00 00 15 10 03 02 12 10 03",
    ),
    "B.11.2 DB_READ DB5 DW0..3": (
        "02 04 10 06 10 06 4A 10 10 4A 17 10 04 10 06 10 06 10 06 10 06",
        "10 06 02 16 10 03 10 06 02 00 00 00 00 00 12 34 00 10 10 AB CD 10 10 10 10 10 03"
        " 02 12 10 03",
    ),
    "B.11.3 DB_WRITE DB5 DW2..3": (
        "02 03 10 06 10 06 4A 14 01 02 10 10 03 10 04 10 06 10 06",
        "10 06 02 16 10 03 10 06 02 12 10 03",
    ),
}


def golden_memory_responder(fn: int, params: bytes) -> bytes | bool | None:
    """A minimal AG for the goldens: DB5 at 4A06h (B.11 scenario); False = refuse."""
    image = bytearray(0x10000)
    image[0x4A06:0x4A10] = h("70 70 41 05 00 00 00 00 00 15")
    image[0x4A10:0x4A18] = h("12 34 00 10 AB CD 10 10")
    image[0xEE00:0xEE04] = h("01 02 03 04")
    if fn == 0x1A:
        if params != h("01 05"):
            return False
        return h("00 4A 10") + bytes(image[0x4A06:0x4A10])
    if fn == 0x04:
        start, end = struct.unpack(">HH", params)
        return bytes(5) + bytes(image[start : end + 1])
    if fn == 0x03:
        return None
    if fn == 0x18:
        return unstuff(h(SYSPAR))
    return False


def run_pg(job: Job, steps: list[tuple[str, bytes]], *, by_byte: bool = False) -> Response | Nak:
    """Run ``steps`` on a PG; ``by_byte``: each AG answer one byte per ``receive_data`` call."""
    pg = PGConnection()
    now = 0.0
    pg.submit(job, now)
    sent = pg.data_to_send()
    expected = b""
    for direction, data in steps:
        if direction == "PG":
            expected += data
            continue
        assert sent == expected, f"PG sent {sent.hex(' ')}, spec says {expected.hex(' ')}"
        sent, expected = b"", b""
        now += 0.01
        for chunk in [bytes([b]) for b in data] if by_byte else [data]:
            pg.receive_data(chunk, now)
        sent = pg.data_to_send()
    assert sent == expected
    event = pg.next_event()
    assert isinstance(event, Response | Nak)
    assert pg.state is PGState.IDLE
    return event


def run_ag(steps: list[tuple[str, bytes]]) -> list[object]:
    ag = AGConnection()
    now = 0.0
    expected = b""
    sent = b""
    events: list[object] = []
    for direction, data in steps:
        if direction == "AG":
            expected += data
            continue
        assert sent == expected, f"AG sent {sent.hex(' ')}, spec says {expected.hex(' ')}"
        sent, expected = b"", b""
        now += 0.01
        ag.receive_data(data, now)
        while (event := ag.next_event()) is not NEED_DATA:
            events.append(event)
            if isinstance(event, Request):
                answer = golden_memory_responder(event.fn, event.params)
                if answer is False:
                    ag.refuse(now)
                else:
                    assert not isinstance(answer, bool)
                    ag.respond(answer, now)
        sent = ag.data_to_send()
    assert sent == expected
    return events


@pytest.mark.parametrize("name", sorted(GOLDENS))
def test_golden_pg_side(name: str) -> None:
    job, steps, result = GOLDENS[name]
    event = run_pg(job, steps)
    assert event == Response(job.fn, result)


@pytest.mark.parametrize("name", sorted(GOLDENS))
def test_golden_ag_side(name: str) -> None:
    job, steps, _ = GOLDENS[name]
    events = run_ag(steps)
    assert events[0] == Request(job.fn, job.params)
    assert events[-1] == Done(job.fn)


@pytest.mark.parametrize("name", sorted(STREAMS))
def test_golden_streams_match_step_tables(name: str) -> None:
    pg_stream, ag_stream = STREAMS[name]
    _, steps, _ = GOLDENS[name]
    assert b"".join(b for d, b in steps if d == "PG") == h(pg_stream)
    assert b"".join(b for d, b in steps if d == "AG") == h(ag_stream)


def test_golden_answers_decode() -> None:
    info = as511.parse_b_info(GOLDENS["B.11.1 B_INFO DB5"][2], 1, 5)
    assert info is not None
    assert (info.dw0, info.length_words, info.data_bytes) == (0x4A10, 0x15, 32)
    data = as511.parse_read(GOLDENS["B.11.2 DB_READ DB5 DW0..3"][2], 8, strict=True)
    assert struct.unpack(">4H", data) == (0x1234, 0x0010, 0xABCD, 0x1010)
    sysp = as511.parse_system_parameters(GOLDENS["B.11.4 system parameters"][2])
    assert (sysp.inputs, sysp.outputs, sysp.flags) == (0xEF00, 0xEF80, 0xEE00)
    assert (sysp.timers, sysp.counters, sysp.system_data) == (0xED00, 0xEC00, 0xEA00)
    assert sysp.end_of_ram == 0x7FFF
    # signature check failures: wrong number, wrong type, not valid, short
    good = GOLDENS["B.11.1 B_INFO DB5"][2]
    assert as511.parse_b_info(good, 1, 6) is None
    assert as511.parse_b_info(good, 0x0C, 5) is None
    assert as511.parse_b_info(good[:12], 1, 5) is None
    assert as511.parse_b_info(b"\x01" + good[1:], 1, 5) is None


def test_golden_missing_block_nak_pg() -> None:
    """B.11.4: B_INFO of a missing DB7 -> DLE NAK at step 9; PG aborts and backs off 500 ms."""
    steps = [*seq("1A", "01 07 10 04", None)[:8], ("AG", h("10 15"))]
    pg = PGConnection()
    pg.submit(as511.b_info_job(1, 7), 0.0)
    out = pg.data_to_send()
    now = 0.0
    expected = b""
    for direction, data in steps:
        if direction == "PG":
            expected += data
            continue
        assert out == expected
        expected = b""
        now += 0.01
        pg.receive_data(data, now)
        out = pg.data_to_send()
    assert out == b""  # nothing after the NAK
    assert pg.next_event() == Nak(0x1A, "params")
    assert pg.ready_at == pytest.approx(now + 0.5)
    with pytest.raises(LocalProtocolError):
        pg.submit(as511.b_info_job(1, 7), now + 0.4)
    pg.receive_data(b"\x00", now + 0.3)  # line noise extends the silence
    assert pg.ready_at == pytest.approx(now + 0.8)
    pg.submit(as511.b_info_job(1, 7), now + 0.8)
    assert pg.data_to_send() == b"\x02"


def test_golden_missing_block_nak_ag() -> None:
    ag = AGConnection()
    ag.receive_data(h("02"), 0)
    assert ag.data_to_send() == h("10 06")
    ag.receive_data(h("1A"), 0)
    assert ag.data_to_send() == h("02")
    ag.receive_data(h("10 06"), 0)
    assert ag.data_to_send() == h("16 10 03")
    ag.receive_data(h("10 06 01 07 10 04"), 0)
    assert ag.next_event() == Request(0x1A, h("01 07"))
    ag.refuse(0)
    assert ag.data_to_send() == h("10 15")
    assert ag.state is AGState.IDLE


def test_nak_at_ready_and_function_steps() -> None:
    pg = PGConnection()
    pg.submit(as511.system_parameters_job(), 0)
    pg.data_to_send()
    pg.receive_data(h("10 15"), 0.01)
    assert pg.next_event() == Nak(0x18, "ready")
    pg.submit(as511.system_parameters_job(), 1.0)
    assert pg.data_to_send() == h("02")
    pg.receive_data(h("10 06"), 1.01)
    assert pg.data_to_send() == h("18")
    pg.receive_data(h("10 15"), 1.02)
    assert pg.next_event() == Nak(0x18, "function")
    # AG side: busy NAK and unsupported function NAK
    ag = AGConnection()
    ag.busy = True
    ag.receive_data(h("02"), 0)
    assert ag.data_to_send() == h("10 15")
    ag.busy = False
    ag.receive_data(h("02 07"), 0)
    assert ag.data_to_send() == h("10 06 10 15")
    assert ag.state is AGState.IDLE


def test_pg_timeouts_and_deadlines() -> None:
    pg = PGConnection(char_timeout=0.5, tx_byte_time=0.001)
    pg.submit(as511.read_job(0, 4), 10.0)
    assert pg.deadline == pytest.approx(10.501)
    pg.timer(10.4)
    assert pg.next_event() is NEED_DATA
    pg.timer(10.6)
    assert pg.next_event() == Timeout(0x04, "W_ACK1")
    assert pg.ready_at == pytest.approx(11.1)
    # a late byte after the deadline aborts even if timer() was not called
    pg.submit(as511.read_job(0, 4), 11.1)
    pg.data_to_send()
    pg.receive_data(h("10 06"), 11.9)
    assert pg.next_event() == Timeout(0x04, "W_ACK1")
    assert pg.data_to_send() == b""


def test_pg_write_deadline_includes_line_time() -> None:
    pg = PGConnection(char_timeout=0.5, tx_byte_time=0.001)
    data = bytes(512)
    pg.submit(as511.write_job(0x100, data), 0)
    pg.data_to_send()
    pg.receive_data(h("10 06"), 0.01)
    pg.receive_data(h("02"), 0.02)
    pg.data_to_send()
    pg.receive_data(h("16 10 03"), 0.03)
    sent = pg.data_to_send()
    assert sent.endswith(h("10 04")) and len(sent) == 2 + 2 + 512 + 2
    assert pg.deadline == pytest.approx(0.03 + 0.5 + len(sent) * 0.001)


def test_pg_lenient_terminate_bytes() -> None:
    for term in ("11 10 03", "14 10 03", "10 03"):
        steps = seq("03", "00 10 10 01 10 04", None)
        steps[-2] = ("AG", h(term))
        assert run_pg(as511.write_job(0x0010, b"\x01"), steps) == Response(3, b"")


def test_pg_rejects_garbage_with_remote_protocol_error() -> None:
    pg = PGConnection()
    pg.submit(as511.read_job(0, 2), 0)
    pg.receive_data(h("10 06 02 16 10 03 10 06 02 00 10 07"), 0.01)
    with pytest.raises(RemoteProtocolError, match="DLE followed by 07h"):
        pg.next_event()
    assert pg.state is PGState.IDLE and pg.ready_at == pytest.approx(0.51)


def test_pg_overlong_answer_is_cut() -> None:
    pg = PGConnection()
    pg.submit(as511.read_job(0, 2), 0)
    pg.receive_data(h("10 06 02 16 10 03 10 06 02") + bytes(100), 0.01)
    with pytest.raises(RemoteProtocolError, match="longer than"):
        pg.next_event()


def test_pg_misuse() -> None:
    pg = PGConnection()
    pg.submit(as511.read_job(0, 2), 0)
    with pytest.raises(LocalProtocolError):
        pg.submit(as511.read_job(0, 2), 0)
    with pytest.raises(LocalProtocolError):
        as511.read_job(0xFFFF, 2)
    with pytest.raises(LocalProtocolError):
        as511.write_job(0, b"")
    ag = AGConnection()
    with pytest.raises(LocalProtocolError):
        ag.respond(b"", 0)


def state_of(ag: AGConnection) -> AGState:
    return ag.state  # (a call, so the type checker does not keep an earlier narrowing)


def test_ag_gap_and_restart() -> None:
    ag = AGConnection(char_timeout=0.5)
    ag.receive_data(h("02"), 0)
    ag.receive_data(h("04"), 0.1)
    assert ag.data_to_send() == h("10 06 02")
    ag.timer(0.7)
    assert isinstance(ag.next_event(), Idled)
    assert ag.state is AGState.IDLE
    # a new STX while waiting for DLE ACK starts over (B.9.2 [R])
    ag.receive_data(h("02 04 02"), 1.0)
    assert ag.data_to_send() == h("10 06 02 10 06")
    assert state_of(ag) is AGState.W_FN
    # a doubled function code 10h (D.B9) is taken as 10h and refused here (unsupported)
    ag.receive_data(h("10 10"), 1.0)
    assert ag.data_to_send() == h("10 15")


# -- properties -------------------------------------------------------------------------------
@settings(max_examples=200)
@given(st.binary(max_size=300))
def test_stuff_round_trip(data: bytes) -> None:
    wire = stuff(data) + h("10 03")
    assert unstuff(wire) == data
    assert wire.count(b"\x10") == 2 * data.count(b"\x10") + 1


@settings(max_examples=200)
@given(st.binary(max_size=200), st.data())
def test_unstuffer_any_split(data: bytes, draw: st.DataObject) -> None:
    wire = stuff(data) + h("10 04")
    cuts = sorted(draw.draw(st.lists(st.integers(0, len(wire)), max_size=8)))
    decoder = Unstuffer(as511.EOT)
    done_at = None
    pos = 0
    for cut in [*cuts, len(wire)]:
        for i, byte in enumerate(wire[pos:cut], start=pos):
            if decoder.feed(byte):
                done_at = i
        pos = max(pos, cut)
    assert done_at == len(wire) - 1
    assert decoder.payload() == data


def _transact(
    job: Job, payload: bytes, split_pg: list[int], split_ag: list[int]
) -> tuple[object, list[Request]]:
    """PG and AG machines wired back to back, each direction delivered in arbitrary pieces."""
    pg, ag = PGConnection(), AGConnection()
    now = 0.0
    pg.submit(job, now)
    to_ag, to_pg = bytearray(pg.data_to_send()), bytearray()
    splits = {"pg": list(split_pg), "ag": list(split_ag)}
    requests: list[Request] = []
    for _ in range(10_000):
        if not to_ag and not to_pg:
            break
        now += 0.001
        for name, buf in (("ag", to_ag), ("pg", to_pg)):
            if not buf:
                continue
            n = splits[name].pop(0) if splits[name] else len(buf)
            n = max(1, min(n, len(buf)))
            piece = bytes(buf[:n])
            del buf[:n]
            if name == "ag":
                ag.receive_data(piece, now)
                while (ev := ag.next_event()) is not NEED_DATA:
                    if isinstance(ev, Request):
                        requests.append(ev)
                        ag.respond(payload if job.has_response else None, now)
                to_pg += ag.data_to_send()
            else:
                pg.receive_data(piece, now)
                to_ag += pg.data_to_send()
    return pg.next_event(), requests


@settings(max_examples=150, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.binary(min_size=1, max_size=64),
    st.lists(st.integers(1, 7), max_size=40),
    st.lists(st.integers(1, 7), max_size=40),
)
def test_pg_ag_any_split_same_result(data: bytes, split_pg: list[int], split_ag: list[int]) -> None:
    read = as511.read_job(0x1010, len(data))
    event, requests = _transact(read, bytes(5) + data, split_pg, split_ag)
    assert event == Response(4, bytes(5) + data)
    assert requests == [Request(4, struct.pack(">HH", 0x1010, 0x1010 + len(data) - 1))]
    write = as511.write_job(0x1010, data)
    event, requests = _transact(write, b"", split_pg, split_ag)
    assert event == Response(3, b"")
    assert requests == [Request(3, b"\x10\x10" + data)]  # the encoded request round-trips


@settings(max_examples=200)
@given(st.lists(st.binary(min_size=1, max_size=20), max_size=10))
def test_random_bytes_never_crash_pg(chunks: list[bytes]) -> None:
    pg = PGConnection()
    now = 0.0
    pg.submit(as511.read_job(0x4A10, 8), now)
    for chunk in chunks:
        now += 0.01
        pg.receive_data(chunk, now)
        pg.data_to_send()
        try:
            event = pg.next_event()
        except RemoteProtocolError:
            event = None
        if event is not NEED_DATA and not pg.busy and now >= pg.ready_at:
            pg.submit(as511.read_job(0x4A10, 8), now)
    pg.timer(now + 10)
    with contextlib.suppress(RemoteProtocolError):
        pg.next_event()
    assert not pg.busy and pg.deadline is None


@settings(max_examples=200)
@given(st.lists(st.binary(min_size=1, max_size=20), max_size=12))
def test_random_bytes_never_crash_ag(chunks: list[bytes]) -> None:
    ag = AGConnection()
    now = 0.0
    for chunk in chunks:
        now += 0.01
        ag.receive_data(b"\x02" + chunk, now)  # an STX first so the machine leaves IDLE
        ag.data_to_send()
        while (ev := ag.next_event()) is not NEED_DATA:
            if isinstance(ev, Request):
                if ev.fn == 0x04:
                    ag.respond(bytes(5) + ev.params, now)
                else:
                    ag.refuse(now)
    ag.timer(now + 10)
    assert ag.state in (AGState.IDLE, AGState.EXECUTE)
