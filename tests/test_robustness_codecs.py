"""The codec rule under every simulator and client: whatever bytes arrive, in whatever pieces, a
codec raises nothing but ``RemoteProtocolError`` (and the AS511 AG nothing at all). One property
across the PLC-side codecs of all protocols, as the simulators use them."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import AGConnection
from plcstack.codecs.e71 import Code, E71ServerConnection
from plcstack.codecs.e71_buffers import FixedBufferConnection, RawBufferConnection
from plcstack.codecs.e71_commands import DECODERS
from plcstack.codecs.fetchwrite import ServerConnection as FwServer
from plcstack.codecs.mk import MkConnection
from plcstack.codecs.s5lan import ServerConnection as S5Server
from plcstack.errors import RemoteProtocolError

FACTORIES: dict[str, Callable[[], Any]] = {
    "e71-tcp-binary": lambda: E71ServerConnection(Code.BINARY, extensions=DECODERS),
    "e71-tcp-ascii": lambda: E71ServerConnection(Code.ASCII, extensions=DECODERS),
    "e71-udp-binary": lambda: E71ServerConnection(
        Code.BINARY, transport="udp", extensions=DECODERS
    ),
    "e71-fixed-binary": lambda: FixedBufferConnection(Code.BINARY, role="e71"),
    "e71-fixed-ascii": lambda: FixedBufferConnection(Code.ASCII, role="e71"),
    "e71-raw": RawBufferConnection,
    "s5lan": S5Server,
    "fetchwrite-raw": lambda: FwServer("raw"),
    "fetchwrite-mk": lambda: FwServer("mk", mk=MkConnection(strict=True)),
}

#: bytes with a bias towards each protocol's structure bytes, so frames get started often
_BYTES = st.lists(
    st.one_of(
        st.binary(max_size=40),
        st.sampled_from(
            [b"S5", b"\x03\x05", b"\x03\x03", b"\x01\xff", b"\x60", b"\x00\x00", b"\x10\x02"]
        ),
    ),
    max_size=12,
)


@pytest.mark.slow  # ~6 s for all codecs; the end-to-end simulator fuzz is the fast check
@pytest.mark.parametrize("name", sorted(FACTORIES))
@settings(max_examples=150, deadline=None)
@given(chunks=_BYTES)
def test_plc_side_codec_raises_only_remote_protocol_error(name: str, chunks: list[bytes]) -> None:
    codec = FACTORIES[name]()
    for chunk in chunks:
        try:
            codec.receive_data(chunk)
            for _ in range(100):  # bounded: a codec never yields events for ever
                if codec.next_event() is NEED_DATA:
                    break
        except RemoteProtocolError:
            return  # the connection is closed here; nothing more is fed


@pytest.mark.slow
@settings(max_examples=150, deadline=None)
@given(chunks=_BYTES, gaps=st.lists(st.floats(0, 2), min_size=12, max_size=12))
def test_as511_ag_never_raises(chunks: list[bytes], gaps: list[float]) -> None:
    ag = AGConnection(char_timeout=0.5)
    now = 0.0
    for chunk, gap in zip(chunks, gaps, strict=False):
        now += gap
        ag.timer(now)
        ag.receive_data(chunk, now)
        for _ in range(100):
            event = ag.next_event()
            if event is NEED_DATA:
                break
            if type(event).__name__ == "Request":
                ag.respond(b"\x00\x01", now)
        ag.data_to_send()
