"""Every codec has the same shape (h11/wsproto style), and a broken stream stays broken.

* each protocol module has a ``ClientConnection`` and a ``ServerConnection`` (the older and the
  manual's names are aliases of the same classes);
* every event derives from :class:`plcstack.codecs.Event`;
* ``send(event) -> bytes`` on the sides that used to have their own verbs gives the same bytes;
* after a :class:`RemoteProtocolError` the E71, FETCH/WRITE and MK connections are in the ERROR
  state: every further call raises :class:`LocalProtocolError` (S5-LAN already did).
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable
from types import ModuleType
from typing import Any

import pytest

from plcstack.codecs import (
    NEED_DATA,
    Event,
    as511,
    e71,
    e71_buffers,
    e71_commands,
    fetchwrite,
    mk,
    s5lan,
)
from plcstack.codecs.e71_buffers import FixedBufferAck, FixedBufferConnection, FixedBufferData
from plcstack.errors import LocalProtocolError, RemoteProtocolError

PROTOCOLS = [e71, s5lan, fetchwrite, as511]


@pytest.mark.parametrize("module", PROTOCOLS, ids=lambda m: m.__name__)
def test_client_and_server_connections_are_named_alike(module: ModuleType) -> None:
    for role in ("ClientConnection", "ServerConnection"):
        cls = getattr(module, role)
        assert inspect.isclass(cls) and role in module.__all__
        for method in ("receive_data", "next_event"):
            assert callable(getattr(cls, method)), (cls, method)
    for cls in (e71.ClientConnection, e71.ServerConnection, s5lan.ServerConnection):
        assert callable(cls.send)


def test_old_and_manual_names_are_aliases() -> None:
    assert e71.E71ClientConnection is e71.ClientConnection
    assert e71.E71ServerConnection is e71.ServerConnection
    assert as511.PGConnection is as511.ClientConnection
    assert as511.AGConnection is as511.ServerConnection


def _dataclasses(module: ModuleType) -> list[type]:
    return [
        obj
        for obj in vars(module).values()
        if inspect.isclass(obj)
        and dataclasses.is_dataclass(obj)
        and obj.__module__ == module.__name__
    ]


#: dataclasses of the codec modules that are values inside events, not events
NOT_EVENTS = {"Header", "Job", "SystemAddresses", "BlockInfo", "DeviceRef"}


@pytest.mark.parametrize(
    "module",
    [e71_commands, e71_buffers, s5lan, fetchwrite, mk, as511],
    ids=lambda m: m.__name__,
)
def test_every_event_derives_from_event(module: ModuleType) -> None:
    classes = [c for c in _dataclasses(module) if c.__name__ not in NOT_EVENTS]
    assert classes
    assert [c.__name__ for c in classes if not issubclass(c, Event)] == []


def test_e71_events_derive_from_event() -> None:
    names = ["Ack", "BitsResponse", "WordsResponse", "ErrorResponse", "OpaqueRequest", "BadRequest"]
    names += [t.__name__ for t in e71.REQUEST_TYPES]
    assert all(issubclass(getattr(e71, n), Event) for n in names)
    assert issubclass(e71.ExtensionRequest, Event) and issubclass(e71.ExtensionResponse, Event)


# -- send(event) ---------------------------------------------------------------------------


def test_mk_send_event_equals_its_verbs() -> None:
    a, b = mk.MkConnection(), mk.MkConnection()
    assert a.send(mk.Message(b"hello")) == b.send_message(b"hello")
    assert a.send(mk.LifeAck(7)) == b.life_ack()
    with pytest.raises(LocalProtocolError):
        a.send(object())  # type: ignore[arg-type]


def test_s5lan_server_send_event_equals_send_response() -> None:
    request = s5lan.Request.read("D", "W", 5, 2, db=10)
    server = s5lan.ServerConnection()
    event = server.answer(request.header, 0, b"\x00\x01\x00\x02")
    assert isinstance(event, s5lan.Response) and isinstance(event, Event)
    assert server.send(event) == server.send_response(request.header, 0, b"\x00\x01\x00\x02")
    with pytest.raises(LocalProtocolError):
        server.answer(request.header, 0, b"\x00")  # a read answer of the wrong size


def test_fixed_buffer_send_event_equals_its_verbs() -> None:
    a = FixedBufferConnection("binary", role="partner")
    b = FixedBufferConnection("binary", role="partner")
    assert a.send(FixedBufferData((1, 2))) == b.send_data([1, 2])
    e71_side = FixedBufferConnection("binary", role="e71")
    e71_side.receive_data(b"\x60\x00\x01\x00\x05\x00")  # one word: 0005H
    assert isinstance(e71_side.next_event(), FixedBufferData)
    assert e71_side.send(FixedBufferAck(0)) == b"\xe0\x00"


# -- the ERROR state -------------------------------------------------------------------------


def _e71_tcp() -> tuple[Any, Callable[[Any], bytes]]:
    codec = e71.ClientConnection("binary")
    codec.send(e71.ReadWords(e71.parse_address("D0"), 1))
    codec.receive_data(b"\x99\x00\x00\x00")  # subheader 99H does not answer 01H
    return codec, lambda c: c.send(e71.ReadWords(e71.parse_address("D0"), 1))


def _e71_udp() -> tuple[Any, Callable[[Any], bytes]]:
    codec = e71.ClientConnection("ascii", transport="udp")
    codec.send(e71.ReadWords(e71.parse_address("D0"), 1))
    codec.receive_data(b"8100")  # a datagram too short for one word
    return codec, lambda c: c.send(e71.ReadWords(e71.parse_address("D0"), 1))


def _fw_client_raw() -> tuple[Any, Callable[[Any], bytes]]:
    codec = fetchwrite.ClientConnection()
    request = fetchwrite.FetchRequest(fetchwrite.Org.MB, 0, 0, 1)
    codec.send(request)
    codec.receive_data(b"XX" + bytes(14))  # not an 'S5' acknowledgement
    return codec, lambda c: c.send(request)


def _fw_client_mk() -> tuple[Any, Callable[[Any], bytes]]:
    codec = fetchwrite.ClientConnection("mk")
    request = fetchwrite.FetchRequest(fetchwrite.Org.MB, 0, 0, 1)
    codec.send(request)
    codec.receive_data(b"NO" + bytes(6))  # not an MK telegram
    return codec, lambda c: c.send(request)


def _fw_server() -> tuple[Any, Callable[[Any], bytes]]:
    codec = fetchwrite.ServerConnection()
    codec.receive_data(b"XX" + bytes(14))  # not an 'S5' request header
    return codec, lambda c: c.send(fetchwrite.WriteResponse(0))


def _mk() -> tuple[Any, Callable[[Any], bytes]]:
    codec = mk.MkConnection()
    codec.receive_data(b"NO" + bytes(6))
    return codec, lambda c: c.send_message(b"x")


@pytest.mark.parametrize(
    "make", [_e71_tcp, _e71_udp, _fw_client_raw, _fw_client_mk, _fw_server, _mk]
)
def test_remote_protocol_error_leaves_the_connection_in_error(
    make: Callable[[], tuple[Any, Callable[[Any], bytes]]],
) -> None:
    codec, send = make()
    assert not codec.errored
    with pytest.raises(RemoteProtocolError) as first:
        codec.next_event()
    assert codec.errored and codec.error is first.value
    for call in (codec.next_event, lambda: codec.receive_data(b"\x00"), lambda: send(codec)):
        with pytest.raises(LocalProtocolError, match="ERROR state after: ") as later:
            call()
        assert first.value.message in later.value.message


def test_a_good_exchange_never_enters_error() -> None:
    codec = e71.ClientConnection("binary")
    codec.send(e71.ReadWords(e71.parse_address("D0"), 1))
    codec.receive_data(b"\x81\x00\x34\x12")
    assert codec.next_event() == e71.WordsResponse(1, (0x1234,))
    assert not codec.errored and codec.next_event() is NEED_DATA
