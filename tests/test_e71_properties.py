"""Hypothesis properties of the E71 codec: round trips for every command and device, split
invariance of the TCP decoders (both roles), and arbitrary bytes never escaping as anything but
RemoteProtocolError (client) or an end code (server)."""

from __future__ import annotations

import contextlib
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import (
    REQUEST_RULES,
    Ack,
    BadRequest,
    BitsResponse,
    Code,
    CpuGroup,
    Device,
    DeviceRef,
    E71ClientConnection,
    E71ServerConnection,
    ErrorResponse,
    MonitorBits,
    MonitorWords,
    OpaqueRequest,
    ReadBits,
    ReadWords,
    RegisterMonitorBits,
    RegisterMonitorWords,
    Request,
    Response,
    TestBits,
    TestWords,
    WordsResponse,
    WriteBits,
    WriteWords,
)
from plcstack.errors import RemoteProtocolError
from plcstack.sim.e71 import execute
from plcstack.sim.melsec_memory import CpuState, MelsecMemory

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

codes = st.sampled_from([Code.BINARY, Code.ASCII])
headers = st.fixed_dictionaries({"pc": st.integers(0, 0xFF), "timer": st.integers(0, 0xFFFF)})
bit_devices = st.sampled_from([d for d in Device if d.is_bit])
word_devices = st.sampled_from([d for d in Device if not d.is_bit])
numbers = st.integers(0, 0xFFFFFFFF)


@st.composite
def bit_refs(draw: st.DrawFn) -> DeviceRef:
    return DeviceRef(draw(bit_devices), draw(numbers))


@st.composite
def word_unit_refs(draw: st.DrawFn) -> DeviceRef:
    """Any device as the head of a word-unit access: bit devices on a 16-point boundary."""
    device = draw(st.sampled_from(list(Device)))
    number = draw(numbers)
    if device is Device.M and number >= 9000:
        number -= (number - 9000) % 16  # special relays: 9000 + a multiple of 16 (§6.2)
    elif device.is_bit:
        number -= number % 16
    return DeviceRef(device, number)


words = st.integers(0, 0xFFFF)


@st.composite
def requests(draw: st.DrawFn) -> Request:
    kind = draw(st.integers(0, 9))
    hdr: dict[str, Any] = draw(headers)
    if kind == 0:
        return ReadBits(draw(bit_refs()), draw(st.integers(1, 256)), **hdr)
    if kind == 1:
        ref = draw(word_unit_refs())
        return ReadWords(ref, draw(st.integers(1, 128 if ref.device.is_bit else 256)), **hdr)
    if kind == 2:
        values = draw(st.lists(st.booleans(), min_size=1, max_size=256))
        return WriteBits(draw(bit_refs()), tuple(values), **hdr)
    if kind == 3:
        ref = draw(word_unit_refs())
        size = 40 if ref.device.is_bit else 256
        return WriteWords(ref, tuple(draw(st.lists(words, min_size=1, max_size=size))), **hdr)
    if kind == 4:
        pts = draw(st.lists(st.tuples(bit_refs(), st.booleans()), min_size=1, max_size=80))
        return TestBits(tuple(pts), **hdr)
    if kind == 5:
        pts = draw(st.lists(st.tuples(word_unit_refs(), words), min_size=1, max_size=40))
        return TestWords(tuple(pts), **hdr)
    if kind == 6:
        return RegisterMonitorBits(
            tuple(draw(st.lists(bit_refs(), min_size=1, max_size=40))), **hdr
        )
    if kind == 7:
        refs = draw(st.lists(word_unit_refs(), min_size=1, max_size=20))
        return RegisterMonitorWords(tuple(refs), **hdr)
    if kind == 8:
        return MonitorBits(**hdr)
    return MonitorWords(**hdr)


def _monitor_sized(client: E71ClientConnection, m: int) -> None:
    client.monitor_bits = m
    client.monitor_words = m


@st.composite
def responses_for(draw: st.DrawFn, req: Request, m: int) -> Response:
    """A plausible response to ``req`` (``m`` = registered monitor points)."""
    cmd = req.COMMAND
    if draw(st.integers(0, 4)) == 0:
        end = draw(st.sampled_from([0x50, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5B, 0x60, 0x99]))
        return ErrorResponse(cmd, end, draw(st.integers(0, 0xFF)) if end == 0x5B else None)
    if isinstance(req, (ReadBits, MonitorBits)):
        n = req.count if isinstance(req, ReadBits) else m
        return BitsResponse(cmd, tuple(draw(st.lists(st.booleans(), min_size=n, max_size=n))))
    if isinstance(req, (ReadWords, MonitorWords)):
        n = req.count if isinstance(req, ReadWords) else m
        return WordsResponse(cmd, tuple(draw(st.lists(words, min_size=n, max_size=n))))
    return Ack(cmd)


@SETTINGS
@given(code=codes, req=requests())
def test_request_round_trip(code: Code, req: Request) -> None:
    client = E71ClientConnection(code)
    _monitor_sized(client, 1)
    wire = client.send(req)
    for transport in ("tcp", "udp"):
        server = E71ServerConnection(code, transport=transport)
        server.receive_data(wire)
        assert server.next_event() == req
        assert server.next_event() is NEED_DATA


@SETTINGS
@given(code=codes, data=st.data(), m=st.integers(1, 40), trailer=st.booleans())
def test_response_round_trip(code: Code, data: st.DataObject, m: int, trailer: bool) -> None:
    req = data.draw(requests())
    resp = data.draw(responses_for(req, m))
    server = E71ServerConnection(code, abnormal_trailer=trailer)
    wire = server.send(resp)
    for transport in ("tcp", "udp"):
        client = E71ClientConnection(code, transport=transport)
        _monitor_sized(client, m)
        client.send(req)
        client.receive_data(wire)
        assert client.next_event() == resp
        assert client.next_event() is NEED_DATA


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    chunks, last = [], 0
    for p in [*points, len(data)]:
        chunks.append(data[last:p])
        last = p
    return chunks


def _drain(conn: E71ServerConnection | E71ClientConnection) -> list[Any]:
    out = []
    while (event := conn.next_event()) is not NEED_DATA:
        out.append(event)
    return out


@SETTINGS
@given(
    code=codes,
    reqs=st.lists(requests(), min_size=1, max_size=5),
    cuts=st.lists(st.integers(0, 10_000), max_size=12),
)
def test_server_split_invariance(code: Code, reqs: list[Request], cuts: list[int]) -> None:
    client = E71ClientConnection(code)
    _monitor_sized(client, 1)
    stream = b"".join(client.send(r) for r in reqs)
    server = E71ServerConnection(code)
    events = []
    for chunk in _split(stream, cuts):
        server.receive_data(chunk)
        events.extend(_drain(server))
    assert events == reqs
    assert server.buffered == 0


@SETTINGS
@given(
    code=codes,
    data=st.data(),
    m=st.integers(1, 40),
    cuts=st.lists(st.integers(0, 10_000), max_size=12),
)
def test_client_split_invariance(code: Code, data: st.DataObject, m: int, cuts: list[int]) -> None:
    # Registrations change how later monitor answers are sized; they are covered elsewhere.
    no_registration = requests().filter(
        lambda r: not isinstance(r, (RegisterMonitorBits, RegisterMonitorWords))
    )
    reqs = data.draw(st.lists(no_registration, min_size=1, max_size=5))
    resps = [data.draw(responses_for(r, m)) for r in reqs]
    trailer = data.draw(st.booleans())
    server = E71ServerConnection(code, abnormal_trailer=trailer)
    stream = b"".join(server.send(r) for r in resps)
    client = E71ClientConnection(code)
    _monitor_sized(client, m)
    for r in reqs:
        client.send(r)
    events = []
    for chunk in _split(stream, cuts):
        client.receive_data(chunk)
        events.extend(_drain(client))
    assert events == resps


@SETTINGS
@given(code=codes, data=st.binary(max_size=300), transport=st.sampled_from(["tcp", "udp"]))
def test_server_never_raises_on_garbage(code: Code, data: bytes, transport: str) -> None:
    server = E71ServerConnection(code, transport=transport)  # type: ignore[arg-type]
    server.receive_data(data)
    for event in _drain(server):
        assert isinstance(event, (BadRequest, OpaqueRequest, *_REQUEST_TYPES))
        if isinstance(event, BadRequest):
            # every refusal encodes to sub|80H + end code
            assert server.send(ErrorResponse(event.command, event.end_code))


_REQUEST_TYPES = (
    ReadBits,
    ReadWords,
    WriteBits,
    WriteWords,
    TestBits,
    TestWords,
    RegisterMonitorBits,
    RegisterMonitorWords,
    MonitorBits,
    MonitorWords,
)


@SETTINGS
@given(
    code=codes,
    data=st.binary(max_size=200),
    req=requests(),
    transport=st.sampled_from(["tcp", "udp"]),
)
def test_client_garbage_raises_only_remote_protocol_error(
    code: Code, data: bytes, req: Request, transport: str
) -> None:
    client = E71ClientConnection(code, transport=transport)  # type: ignore[arg-type]
    _monitor_sized(client, 3)
    client.send(req)
    client.receive_data(data)
    with contextlib.suppress(RemoteProtocolError):
        _drain(client)


@SETTINGS
@given(code=codes, data=st.text(alphabet="0123456789ABCDEFabcdef", max_size=120))
def test_ascii_hex_garbage_is_framed_or_refused(code: Code, data: str) -> None:
    """Hex-only garbage exercises the ASCII sizing paths more deeply than random bytes."""
    server = E71ServerConnection(Code.ASCII)
    server.receive_data(data.encode())
    _drain(server)


def test_every_defined_subheader_has_a_length_rule() -> None:
    defined = set(range(0x00, 0x22)) | set(range(0x39, 0x3D)) | {0x60, 0x61, 0x62}
    assert set(REQUEST_RULES) == defined


@SETTINGS
@given(
    req=requests(),
    state=st.sampled_from(list(CpuState)),
    write_in_run=st.booleans(),
    group=st.sampled_from(list(CpuGroup)),
    code=codes,
)
def test_simulator_answers_every_request(
    req: Request, state: CpuState, write_in_run: bool, group: CpuGroup, code: Code
) -> None:
    """Whatever a partner sends, the simulated E71 answers with an encodable response."""
    mem = MelsecMemory(group, state=state, write_in_run=write_in_run)
    resp = execute(mem, req)
    assert resp.command == req.COMMAND
    assert E71ServerConnection(code).send(resp)


@SETTINGS
@given(code=codes, data=st.binary(max_size=300))
def test_simulator_answers_garbage(code: Code, data: bytes) -> None:
    mem = MelsecMemory()
    server = E71ServerConnection(code)
    server.receive_data(data)
    for event in _drain(server):
        assert server.send(execute(mem, event))
