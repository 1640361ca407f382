"""Focused regression tests for the defects the cross-protocol robustness audit found."""

from __future__ import annotations

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import (
    ACK,
    DLE,
    EOT,
    FN_READ,
    STX,
    AGConnection,
    AGState,
    Idled,
    Request,
)


def _events(ag: AGConnection) -> list[object]:
    out: list[object] = []
    while (event := ag.next_event()) is not NEED_DATA:
        out.append(event)
    return out


def test_as511_request_abandoned_in_the_same_chunk_is_withdrawn() -> None:
    """A PG that sends a whole request and, without waiting, more bytes: the AG drops to idle
    and the Request must not be handed out (answering it raised out of respond())."""
    ag = AGConnection()
    request = bytes([STX, FN_READ, DLE, ACK, DLE, ACK, 0x12, 0x34, 0x00, 0x02, DLE, EOT])
    ag.receive_data(request + b"\x55", now=0.0)
    events = _events(ag)
    assert not any(isinstance(e, Request) for e in events)
    assert any(isinstance(e, Idled) for e in events)
    assert ag.state is AGState.IDLE
    # the same request on its own is still served
    ag.receive_data(request, now=1.0)
    assert [type(e) for e in _events(ag)] == [Request]
    ag.respond(b"\x00\x01", now=1.0)
