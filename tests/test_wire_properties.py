"""Properties of the capture format: whatever a connection sends and receives, in whatever
chunks, the file gives back the same bytes in the same order; and a TCP stream captured with
retransmissions and segments out of order is reassembled to what was sent."""

from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.transports.tap import Endpoints
from plcstack.wire.packets import ACK, PSH, ip_address, tcp_packet
from plcstack.wire.pcapng import (
    LINKTYPE_RAW,
    enhanced_packet,
    interface_description,
    read_capture,
    section_header,
)
from plcstack.wire.recording import Recording
from plcstack.wire.streams import conversations

CHUNKS = st.lists(st.tuples(st.booleans(), st.binary(min_size=1, max_size=300)), max_size=30)


@settings(max_examples=60)
@given(chunks=CHUNKS, kind=st.sampled_from(["tcp", "udp", "serial"]), v6=st.booleans())
def test_what_was_recorded_reads_back_the_same(
    chunks: list[tuple[bool, bytes]], kind: str, v6: bool
) -> None:
    host = "::1" if v6 else "127.0.0.1"
    if kind == "udp":
        # UDP has no handshake: the end that sends first is taken for the client, as in any
        # request/answer protocol
        chunks = [(True, b"?"), *chunks]
    recording = Recording()
    out = recording.header()
    endpoints = (
        Endpoints("serial", ("", 0), ("", 0), "local", "/dev/ttyS9")
        if kind == "serial"
        else Endpoints(kind, (host, 40000), (host, 5000), "local")  # type: ignore[arg-type]
    )
    stream, blocks = recording.open(endpoints, 1)
    out += blocks
    for n, (outbound, data) in enumerate(chunks):
        out += recording.data(stream, outbound, data, 2 + n)
    out += recording.end(stream, False, 100)
    found = conversations(out)
    if not chunks:
        assert all(not c.chunks for c in found)
        return
    (conversation,) = found
    for direction in (True, False):
        expected = b"".join(d for s, d in chunks if s is direction)
        got = b"".join(c.data for c in conversation.chunks if c.from_client is direction)
        assert got == expected
    if kind == "udp":  # datagrams stay datagrams
        assert [(c.from_client, c.data) for c in conversation.chunks] == chunks


@settings(max_examples=60)
@given(data=st.binary(min_size=1, max_size=2000), seed=st.integers(0, 2**32 - 1))
def test_retransmitted_and_reordered_segments_reassemble(data: bytes, seed: int) -> None:
    """Cut into segments, some sent twice, some overlapping what came before, delivered in a
    shuffled order within a small window: the stream read back is the bytes sent."""
    rng = random.Random(seed)
    pc, plc = ip_address("10.0.0.1"), ip_address("10.0.0.5")
    isn = rng.randrange(2**32)
    segments: list[tuple[int, bytes]] = []
    offset = 0
    while offset < len(data):
        size = rng.randrange(1, 200)
        start = max(0, offset - rng.randrange(0, 20)) if rng.random() < 0.2 else offset
        segments.append((start, data[start : offset + size]))
        if rng.random() < 0.2:
            segments.append(segments[-1])  # a retransmission
        offset += size
    # a window of reordering: a segment may overtake the one or two before it
    for i in range(len(segments) - 1, 0, -1):
        if rng.random() < 0.3:
            j = max(0, i - rng.randrange(1, 3))
            segments[i], segments[j] = segments[j], segments[i]
    out = section_header("test") + interface_description(LINKTYPE_RAW, "x")
    syn = tcp_packet(pc, plc, 40000, 5000, isn - 1, 0, 0x02)
    out += enhanced_packet(0, 1, syn)
    for n, (start, part) in enumerate(segments):
        packet = tcp_packet(pc, plc, 40000, 5000, isn + start, 1, PSH | ACK, part)
        out += enhanced_packet(0, 2 + n, packet)
    assert len(list(read_capture(out))) == len(segments) + 1
    (conversation,) = conversations(out)
    assert b"".join(c.data for c in conversation.chunks) == data
    assert conversation.gaps == 0
