"""Issue 16, codec part: every codec fast path decides exactly as the general path it shortcuts.

* E71 ``send`` of a 01H word read in binary: the inlined checks + one ``struct`` call, and the
  reuse of the last bytes for the same request object or a new one made of the very same field
  objects, against the general encoder (``_Header.encode``: checks, then the field writer) and
  against the codec with its fast paths off: same bytes, or the same typed error and message,
  and the same pending requests afterwards. Odd values (bools, floats, out-of-range numbers,
  bit-device heads off a multiple of 16, non-references) included.
* E71 decoding of a normal 01H answer over TCP in one step, against the general framer, on
  random answer streams cut at random places (see also ``tests/test_fleet_paths.py``).
* AS511 PG machine: a whole expected answer (DLE ACK, STX, accept and terminate frame) taken
  as one step, and a data frame un-stuffed with ``bytes.replace``, against the byte-by-byte
  machine (fast paths off, one byte per call) on normal and damaged answer streams with random
  cuts and late chunks: the same bytes sent, state, deadlines, events and errors after every
  chunk; the spec's golden sequences on both paths.
* :func:`plcstack.codecs._common.slot_init`: the replacement ``__init__`` builds the objects the
  generated one builds, with the same signature.
"""

from __future__ import annotations

import dataclasses
import inspect
import itertools
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.bench import frames
from plcstack.codecs import as511
from plcstack.codecs._common import GENERATED_INITS, NEED_DATA
from plcstack.codecs.as511 import (
    Job,
    PGConnection,
    Unstuffer,
    read_job,
    stuff,
    system_parameters_job,
    write_job,
)
from plcstack.codecs.e71 import (
    Code,
    Device,
    DeviceRef,
    E71ClientConnection,
    ReadBits,
    ReadWords,
    WriteWords,
)
from plcstack.codecs.e71_events import _Header, encode_request
from plcstack.codecs.e71_framing import StreamResponses
from plcstack.errors import PlcError
from tests.test_as511_codec import GOLDENS, run_pg

#: examples per property in the default run; the heaviest three also run at 500-600 examples as
#: ``..._at_length`` twins marked slow (``pytest -m slow``, run by CI), seconds of CPU each
DEFAULT_EXAMPLES = 120

_REFS: list[Any] = [
    DeviceRef(Device.D, 0),
    DeviceRef(Device.D, 9000),
    DeviceRef(Device.W, 0x1FF),
    DeviceRef(Device.M, 16),
    DeviceRef(Device.M, 3),  # a bit device head off a multiple of 16: 58H case
    DeviceRef(Device.M, 9008),  # special relays count from 9000
    DeviceRef(Device.X, 0x10),
    DeviceRef(Device.D, 0xFFFFFFFF),
    DeviceRef(Device.D, 1 << 32),  # beyond the field
    DeviceRef(Device.D, -1),
    DeviceRef(Device.D, 1.5),  # type: ignore[arg-type]
    "D0",  # not a reference at all
]
_COUNTS: list[Any] = [0, 1, 2, 64, 128, 129, 255, 256, 257, -1, True, 64.0, 10**20]
_PCS: list[Any] = [0, 0xFF, 0x100, -1, True, 1.0]
_TIMERS: list[Any] = [0, 10, 1000, 0xFFFF, 0x10000, -1, 2.5]


def _outcome(fn: Any) -> Any:
    try:
        return ("bytes", fn())
    except PlcError as exc:
        return ("error", type(exc).__name__, str(exc))


def _general_encoding(request: ReadWords, code: Code) -> Any:
    """The reference: the checks and field writer every 00H-09H request goes through."""
    return _outcome(lambda: _Header.encode(request, code))


_picks = st.tuples(
    st.integers(0, len(_REFS) - 1),
    st.integers(0, len(_COUNTS) - 1),
    st.integers(0, len(_PCS) - 1),
    st.integers(0, len(_TIMERS) - 1),
    st.sampled_from(["new", "same object", "copy", "twin count", "twin pc", "twin timer"]),
)


def _twin(value: Any) -> Any:
    """A value equal to ``value`` but not the same object (a float, or a big int built anew):
    a reuse that compared values instead of identities would take it for the last one."""
    if type(value) is int:
        return float(value) if value < 2**53 else value + 0
    return value


@settings(max_examples=DEFAULT_EXAMPLES, deadline=None)
@given(picks=st.lists(_picks, min_size=1, max_size=8), code=st.sampled_from(list(Code)))
def test_e71_read_words_send_fast_path_is_the_general_encoder(
    picks: list[tuple[int, int, int, int, str]], code: Code
) -> None:
    _e71_read_words_send(picks, code)


@pytest.mark.slow
@settings(max_examples=500, deadline=None)
@given(picks=st.lists(_picks, min_size=1, max_size=8), code=st.sampled_from(list(Code)))
def test_e71_read_words_send_fast_path_is_the_general_encoder_at_length(
    picks: list[tuple[int, int, int, int, str]], code: Code
) -> None:
    _e71_read_words_send(picks, code)


def _e71_read_words_send(picks: list[tuple[int, int, int, int, str]], code: Code) -> None:
    fast = E71ClientConnection(code)
    sent = 0
    last: ReadWords | None = None
    for ref_i, count_i, pc_i, timer_i, how in picks:
        if how == "same object" and last is not None:
            request = last
        elif how == "copy" and last is not None:
            # a new object made of the very same field objects (the reuse-by-identity path)
            request = ReadWords(last.ref, last.count, pc=last.pc, timer=last.timer)
        elif how.startswith("twin") and last is not None:
            fields = {"count": last.count, "pc": last.pc, "timer": last.timer}
            name = how.split()[1]
            fields[name] = _twin(fields[name])
            request = ReadWords(last.ref, **fields)
        else:
            request = ReadWords(
                _REFS[ref_i], _COUNTS[count_i], pc=_PCS[pc_i], timer=_TIMERS[timer_i]
            )
        expected = _general_encoding(request, code)
        assert _outcome(lambda r=request: fast.send(r)) == expected
        sent += expected[0] == "bytes"
        assert fast.pending == sent  # a request is pending exactly when it was encoded
        last = request


@pytest.mark.parametrize("field", ["count", "pc", "timer"])
@pytest.mark.parametrize("value", [True, 1, 10, 64, 255, 1000])
def test_e71_reuse_needs_the_very_same_field_objects(field: str, value: Any) -> None:
    """After a checked read, a new one whose field only *equals* the last one's (a float, a
    bool, a separately built big int) is decided afresh, as the general path decides it."""
    fields: dict[str, Any] = {"count": 1, "pc": 0, "timer": 0}
    fields[field] = value
    for twin in (float(value), bool(value), int(str(int(value)))):
        fast = E71ClientConnection("binary")
        first = ReadWords(_REFS[0], **fields)
        assert _outcome(lambda r=first, c=fast: c.send(r)) == _general_encoding(first, Code.BINARY)
        second = ReadWords(_REFS[0], **{**fields, field: twin})
        assert _outcome(lambda r=second, c=fast: c.send(r)) == _general_encoding(
            second, Code.BINARY
        )


@pytest.mark.parametrize("cls", [ReadBits, ReadWords])
@pytest.mark.parametrize("ref", _REFS, ids=str)
def test_e71_read_encoders_fast_path_is_the_general_encoder(cls: Any, ref: Any) -> None:
    """``ReadBits.encode`` / ``ReadWords.encode`` in binary have their own fast path (used by
    ``encode_request``): the same outcome as the general encoder for every odd value."""
    for count, pc, timer in itertools.product(_COUNTS, _PCS[:4], _TIMERS[:3]):
        request = cls(ref, count, pc=pc, timer=timer)
        expected = _outcome(lambda r=request: _Header.encode(r, Code.BINARY))
        assert _outcome(lambda r=request: r.encode(Code.BINARY)) == expected, request


# -- decoding: a normal 01H answer in one step --------------------------------------------------
_D0 = DeviceRef(Device.D, 0)
_M16 = DeviceRef(Device.M, 16)
_DECODE_REQUESTS: list[Any] = [
    ReadWords(_D0, 64),
    ReadWords(_D0, 256),  # count field 00H
    ReadWords(_M16, 2),  # bit device in words
    ReadBits(_M16, 5),
    WriteWords(_D0, (1, 2)),
    ReadWords(_D0, 1),
]


def _answers_for(request: Any) -> st.SearchStrategy[bytes]:
    sub = bytes([request.COMMAND | 0x80])
    words = 2 * request.count if type(request) is ReadWords else 0
    if type(request) is ReadBits:
        words = (request.count + 1) // 2
    return st.one_of(
        st.binary(min_size=words, max_size=words).map(lambda d: sub + b"\x00" + d),  # normal
        st.binary(max_size=words + 3).map(lambda d: sub + b"\x00" + d),  # normal, odd length
        st.sampled_from([sub + b"\x51", sub + b"\x5b\x10\x00", sub + b"\x5b\x10", b"\x82\x00"]),
        st.binary(max_size=6),
    )


@st.composite
def _streams(draw: st.DrawFn) -> tuple[list[Any], bytes]:
    indices = draw(st.lists(st.integers(0, len(_DECODE_REQUESTS) - 1), min_size=1, max_size=5))
    requests = [_DECODE_REQUESTS[i] for i in indices]
    stream = b"".join(draw(_answers_for(r)) for r in requests)
    return requests, stream


class ReferenceDecoder(E71ClientConnection):
    """The reference for the one-step decoding: every answer cut by the stream framer and
    decoded by the general decoder (the one-step path needs the stream framer it is not given),
    every request encoded by the general encoder."""

    def __init__(self) -> None:
        super().__init__("binary", transport="tcp")
        self._fast_stream = None

    def send(self, request: Any) -> bytes:
        data = encode_request(request, self.code)
        self._pending.append(request)
        return data


def _decode_all(fast: bool, requests: list[Any], stream: bytes, cuts: list[int]) -> list[Any]:
    codec = E71ClientConnection("binary", transport="tcp") if fast else ReferenceDecoder()
    for request in requests:
        codec.send(request)
    out: list[Any] = []
    pieces = [stream[a:b] for a, b in itertools.pairwise([0, *sorted(cuts), len(stream)])]
    for piece in pieces:
        codec.receive_data(piece)
        while True:
            try:
                event = codec.next_event()
            except PlcError as exc:
                out.append(("error", type(exc).__name__, str(exc)))
                out.append(("errored", codec.errored, codec.pending))
                return out
            if event is NEED_DATA:
                break
            out.append(("event", event))
    out.append(("left", codec.pending, len(codec._fast_buffer)))
    return out


@settings(max_examples=DEFAULT_EXAMPLES, deadline=None)
@given(case=_streams(), cuts=st.lists(st.integers(0, 600), max_size=6))
def test_e71_one_step_decoding_is_the_general_decoder(
    case: tuple[list[Any], bytes], cuts: list[int]
) -> None:
    _e71_one_step(case, cuts)


@pytest.mark.slow
@settings(max_examples=500, deadline=None)
@given(case=_streams(), cuts=st.lists(st.integers(0, 600), max_size=6))
def test_e71_one_step_decoding_is_the_general_decoder_at_length(
    case: tuple[list[Any], bytes], cuts: list[int]
) -> None:
    _e71_one_step(case, cuts)


def _e71_one_step(case: tuple[list[Any], bytes], cuts: list[int]) -> None:
    requests, stream = case
    cuts = [c for c in cuts if c <= len(stream)]
    assert _decode_all(True, requests, stream, cuts) == _decode_all(False, requests, stream, cuts)


def test_e71_fast_paths_are_taken(monkeypatch: pytest.MonkeyPatch) -> None:
    """The differential tests above prove nothing if the fast paths never run: a 64-word read
    and its normal answer go through them (no general encoder or framer call)."""
    calls: list[str] = []

    def spy(name: str) -> Any:
        return lambda *args: calls.append(name)

    monkeypatch.setattr(StreamResponses, "next_frame", spy("framer"))
    monkeypatch.setattr(_Header, "encode", spy("encoder"))
    codec = E71ClientConnection("binary")
    data = codec.send(ReadWords(_D0, 64))
    assert codec.send(ReadWords(_D0, 64)) is data  # the same field objects: reused
    answer = b"\x81\x00" + bytes(range(128))
    codec.receive_data(answer + answer)
    first, second = codec.next_event(), codec.next_event()
    assert calls == []
    assert first == second and first.values[0] == 0x0100  # type: ignore[union-attr]


# -- slot_init -------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", sorted(GENERATED_INITS, key=str), ids=lambda c: c.__name__)
def test_slot_init_builds_what_the_generated_init_builds(cls: type) -> None:
    generated = GENERATED_INITS[cls]
    assert inspect.signature(cls.__init__) == inspect.signature(generated)  # type: ignore[misc]
    fields = dataclasses.fields(cls)
    args = {f.name: object() for f in fields}
    built = cls(**args)
    reference: Any = object.__new__(cls)
    generated(reference, **args)
    assert all(getattr(built, f.name) is args[f.name] for f in fields)
    assert all(getattr(reference, f.name) is args[f.name] for f in fields)
    assert built == reference
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(built, fields[0].name, 1)
    # defaults: build with only the fields that have none
    required = {f.name: args[f.name] for f in fields if f.default is dataclasses.MISSING}
    partial = cls(**required)
    for f in fields:
        if f.default is not dataclasses.MISSING:
            assert getattr(partial, f.name) == f.default


# -- AS511: whole answers in one step, a data frame un-stuffed with bytes.replace ----------------
def _as511_jobs() -> st.SearchStrategy[tuple[Job, bytes | None]]:
    """A job and the AG's normal (unstuffed) data frame for it; data full of 10h and 03h."""
    data = st.binary(max_size=40).map(
        lambda b: b.replace(b"\x01", b"\x10").replace(b"\x02", b"\x03")
    )
    reads = st.tuples(st.integers(0, 0x1000), data).map(
        lambda t: (read_job(t[0], len(t[1]) or 1), bytes(5) + (t[1] or b"\x10"))
    )
    writes = st.tuples(st.integers(0x1000, 0x1010), data.filter(bool)).map(
        lambda t: (write_job(t[0], t[1]), None)
    )
    unknown = data.map(lambda d: (system_parameters_job(), b"\x00" + d))  # no length known
    return st.one_of(reads, writes, unknown)


@st.composite
def _as511_dialogues(draw: st.DrawFn) -> tuple[Job, list[tuple[bytes, float]], list[bool]]:
    """A job, the AG's answer stream (normal, or with a byte changed, dropped or added, or a
    different terminate byte), cut into chunks each with its arrival time (sometimes after a
    deadline), and whether to call ``timer`` after each chunk."""
    job, payload = draw(_as511_jobs())
    stream = bytearray(frames._as511_script(job.fn, job.params, payload).expect or b"")
    for _ in range(draw(st.integers(0, 2))):
        where = draw(st.integers(0, len(stream)))
        how = draw(st.sampled_from(["change", "drop", "add", "terminate"]))
        byte = draw(st.sampled_from([0x00, 0x02, 0x03, 0x04, 0x06, 0x10, 0x11, 0x14, 0x15, 0x16]))
        if how == "change" and where < len(stream):
            stream[where] = byte
        elif how == "drop" and where < len(stream):
            del stream[where]
        elif how == "add":
            stream.insert(where, byte)
        elif how == "terminate" and len(stream) >= 3:
            stream[-3:] = draw(st.sampled_from([b"\x11\x10\x03", b"\x14\x10\x03", b"\x10\x03"]))
    cuts = sorted(draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    pieces = [bytes(stream[a:b]) for a, b in itertools.pairwise([0, *cuts, len(stream)])]
    now, chunks = 0.0, []
    for piece in pieces:
        now += draw(st.sampled_from([0.0, 0.001, 0.01, 0.3, 0.6]))
        chunks.append((piece, now))
    return job, chunks, draw(st.lists(st.booleans(), min_size=len(chunks), max_size=len(chunks)))


def _pg_state(pg: PGConnection) -> tuple[Any, ...]:
    events: list[Any] = []
    while True:
        try:
            event = pg.next_event()
        except PlcError as exc:
            events.append(("error", type(exc).__name__, str(exc)))
            continue
        if event is NEED_DATA:
            break
        events.append(event)
    return (
        pg.data_to_send(),
        pg.state,
        pg.deadline,
        pg.ready_at,
        pg.delivery,
        pg._dle,
        pg._got_byte,
        pg._payload,
        None if pg._rx is None else (pg._rx.payload(), pg._rx._dle),
        events,
    )


def _run_pg(fast: bool, job: Job, chunks: list[tuple[bytes, float]], timers: list[bool]) -> Any:
    """The subject gets the chunks as they came; the reference gets them one byte per call, so
    neither a whole answer of several bytes nor a whole data frame is ever seen at once: the
    byte-by-byte machine (``_receive_byte``, ``Unstuffer.feed``), whose transitions the
    whole-answer steps share."""
    pg = PGConnection(char_timeout=0.5, response_timeout=0.7, tx_byte_time=0.0001)
    pg.submit(job, 0.0)
    trace: list[Any] = [_pg_state(pg)]
    for (chunk, now), timer in zip(chunks, timers, strict=True):
        if fast:
            pg.receive_data(chunk, now)
        else:
            for byte in chunk:
                pg.receive_data(bytes([byte]), now)
        if timer:
            pg.timer(now + 0.2)
        trace.append(_pg_state(pg))
    return trace


@settings(max_examples=DEFAULT_EXAMPLES, deadline=None)
@given(dialogue=_as511_dialogues())
def test_as511_whole_answer_steps_are_the_byte_machine(
    dialogue: tuple[Job, list[tuple[bytes, float]], list[bool]],
) -> None:
    _as511_steps(dialogue)


@pytest.mark.slow
@settings(max_examples=600, deadline=None)
@given(dialogue=_as511_dialogues())
def test_as511_whole_answer_steps_are_the_byte_machine_at_length(
    dialogue: tuple[Job, list[tuple[bytes, float]], list[bool]],
) -> None:
    _as511_steps(dialogue)


def _as511_steps(dialogue: tuple[Job, list[tuple[bytes, float]], list[bool]]) -> None:
    job, chunks, timers = dialogue
    assert _run_pg(True, job, chunks, timers) == _run_pg(False, job, chunks, timers)


@settings(max_examples=500, deadline=None)
@given(
    data=st.binary(max_size=60).map(
        lambda b: b.replace(b"\x01", b"\x10").replace(b"\x02", b"\x03")
    ),
    junk=st.binary(max_size=4),
    limit=st.sampled_from([None, 0, 5, 30]),
    draw=st.data(),
)
def test_as511_unstuffer_whole_frame_is_the_byte_decoder(
    data: bytes, junk: bytes, limit: int | None, draw: st.DataObject
) -> None:
    """``Unstuffer.feed_from`` (a whole frame un-stuffed with ``bytes.replace``) against
    ``Unstuffer.feed`` byte by byte: same end, payload and error, on good and broken frames
    (a byte changed into or from DLE, a DLE added or dropped)."""
    wire = bytearray(stuff(data) + b"\x10\x03" + junk)
    for _ in range(draw.draw(st.integers(0, 2))):
        where = draw.draw(st.integers(0, len(wire)))
        how = draw.draw(st.sampled_from(["set", "insert", "drop"]))
        byte = draw.draw(st.sampled_from([0x10, 0x03, 0x00, 0x05]))
        if how == "insert":
            wire.insert(where, byte)
        elif where < len(wire):
            if how == "set":
                wire[where] = byte
            else:
                del wire[where]

    cut = draw.draw(st.integers(0, len(wire)))  # the frame may arrive in two chunks

    def whole() -> Any:
        rx = Unstuffer(as511.ETX, limit)
        try:
            end = rx.feed_from(bytes(wire[:cut]), 0)
            if end < 0:
                end = rx.feed_from(bytes(wire[cut:]), 0)
                end = end if end < 0 else cut + end
            return ("end", end, rx.payload())
        except PlcError as exc:
            return ("error", str(exc))

    def by_byte() -> Any:
        rx = Unstuffer(as511.ETX, limit)
        try:
            for i, byte in enumerate(wire):
                if rx.feed(byte):
                    return ("end", i + 1, rx.payload())
        except PlcError as exc:
            return ("error", str(exc))
        return ("end", -1, rx.payload())

    assert whole() == by_byte()


@pytest.mark.parametrize("by_byte", [False, True], ids=["whole answers", "byte by byte"])
@pytest.mark.parametrize("name", sorted(GOLDENS))
def test_as511_goldens_on_both_paths(name: str, by_byte: bool) -> None:
    """The spec's golden sequences (B.11), each AG answer in one chunk and one byte per call."""
    job, steps, result = GOLDENS[name]
    assert run_pg(job, steps, by_byte=by_byte) == as511.Response(job.fn, result)


def test_as511_fast_paths_are_taken(monkeypatch: pytest.MonkeyPatch) -> None:
    """A normal 64-word read, one chunk per PG step, never goes through the byte path."""
    monkeypatch.setattr(PGConnection, "_receive_byte", lambda *a: pytest.fail("byte path"))
    data = bytes(range(0x08, 0x88))  # holds a 10h
    script = frames._as511_script(4, read_job(0x10, 128).params, bytes(5) + data)
    assert script.expect is not None
    pg = PGConnection()
    pg.submit(read_job(0x10, 128), 0.0)
    pos = 0
    for _send, count in script.steps:
        if count:
            pg.receive_data(script.expect[pos : pos + count], 0.0)
        pos += count
    assert pg.next_event() == as511.Response(4, bytes(5) + data)
