"""The capture tap: who sees every byte a connection sends and receives, with its endpoints.

A :class:`Tap` is asked for a :class:`ConnectionTap` when a connection opens (with its
:class:`Endpoints`) and is then told every chunk sent and received, and the end. Two ways to
attach one:

* ``capturing(tap)``: everything opened inside the ``with`` block (client transports, and the
  simulators' listeners started there) is recorded: the ``--pcap`` of the command line.
* ``transport.record_to(tap)``: one client transport's connections, whatever the context: the
  runtime's flight recorder, one ring per PLC.

Zero cost when off: the tap is looked up once, when a connection opens; without one the
connection uses the plain protocol classes, and its hot path has not one instruction more.
With one, the tapped subclasses record, then do what the plain ones do.

The server side (simulators) gets the same through :func:`start_server`,
:func:`create_server` and :func:`create_datagram_endpoint`: asyncio's own calls when nothing
is captured, a recording wrapper around the protocol and its transport when something is.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import logging
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal, Protocol, cast

__all__ = [
    "ConnectionTap",
    "Endpoints",
    "Tap",
    "Tee",
    "capturing",
    "create_datagram_endpoint",
    "create_server",
    "current_tap",
    "endpoints_of",
    "start_server",
]

log = logging.getLogger(__name__)

Kind = Literal["tcp", "udp", "serial"]


@dataclass(frozen=True, slots=True)
class Endpoints:
    """The two ends of one connection, as the capture file names them.

    ``local``/``remote`` are ``(host, port)`` for TCP and UDP; for a serial line both are
    ``("", 0)`` and ``device`` names the port. ``initiator`` says which end opened it (the
    TCP client): a synthesised handshake goes from that end.
    """

    kind: Kind
    local: tuple[str, int]
    remote: tuple[str, int]
    initiator: Literal["local", "remote"]
    device: str = ""


class ConnectionTap(Protocol):
    """What one connection's recorder is told. Each call records at the time it is made."""

    def sent(self, data: bytes) -> None:
        """We wrote ``data`` (a datagram for UDP)."""

    def received(self, data: bytes) -> None:
        """``data`` arrived (a chunk of the stream, or a datagram)."""

    def ended(self, by_peer: bool) -> None:
        """The connection ended: the peer closed it (``by_peer``), or we did. Called once
        at most; nothing is recorded for the connection after it."""


class Tap(Protocol):
    """A recorder of connections: a capture file, a flight recorder's ring."""

    def connection(self, endpoints: Endpoints) -> ConnectionTap:
        """A connection opened; its bytes go to the returned recorder."""


class Tee:
    """Two taps as one: a connection recorded by both (``--pcap`` and the flight recorder)."""

    def __init__(self, first: Tap, second: Tap) -> None:
        self.first = first
        self.second = second

    def connection(self, endpoints: Endpoints) -> ConnectionTap:
        return _TeeConnection(self.first.connection(endpoints), self.second.connection(endpoints))


class _TeeConnection:
    __slots__ = ("first", "second")

    def __init__(self, first: ConnectionTap, second: ConnectionTap) -> None:
        self.first = first
        self.second = second

    def sent(self, data: bytes) -> None:
        self.first.sent(data)
        self.second.sent(data)

    def received(self, data: bytes) -> None:
        self.first.received(data)
        self.second.received(data)

    def ended(self, by_peer: bool) -> None:
        self.first.ended(by_peer)
        self.second.ended(by_peer)


_CAPTURE: contextvars.ContextVar[Tap | None] = contextvars.ContextVar(
    "plcstack_capture", default=None
)


def current_tap() -> Tap | None:
    """The tap of the ``capturing`` block we run in, if any."""
    return _CAPTURE.get()


@contextlib.contextmanager
def capturing(tap: Tap) -> Iterator[Tap]:
    """Record every connection opened inside the block (and in tasks started from it)."""
    token = _CAPTURE.set(tap)
    try:
        yield tap
    finally:
        _CAPTURE.reset(token)


def combined(own: Tap | None) -> Tap | None:
    """A connection's own tap and the context's, as one (None when neither records)."""
    context = _CAPTURE.get()
    if own is None:
        return context
    if context is None or context is own:
        return own
    return Tee(own, context)


def _address(name: object) -> tuple[str, int]:
    if isinstance(name, tuple | list) and len(name) >= 2:
        return str(name[0]), int(name[1])
    return ("", 0)


def endpoints_of(
    transport: asyncio.BaseTransport,
    kind: Kind,
    initiator: Literal["local", "remote"],
    remote: object = None,
) -> Endpoints:
    """The endpoints of an asyncio transport's socket (``remote`` given for an unconnected
    UDP socket, whose peer differs per datagram)."""
    local = _address(transport.get_extra_info("sockname"))
    peer = _address(remote if remote is not None else transport.get_extra_info("peername"))
    return Endpoints(kind, local, peer, initiator)


def recorded_send(send: Callable[[bytes], None], wire: ConnectionTap) -> Callable[[bytes], None]:
    """``send`` that first tells ``wire`` what it sends: a tapped connection's write path."""

    def send_recorded(data: bytes) -> None:
        wire.sent(bytes(data))
        send(data)

    return send_recorded


# -- the server side: a recording wrapper around a protocol and its transport ------------------


class _TappedTransport(asyncio.Transport):
    """The transport a tapped server protocol is given: records what it writes, then writes
    through the real one; everything else is the real one's."""

    def __init__(self, inner: asyncio.Transport, wire: ConnectionTap, owner: _TappedProtocol):
        super().__init__()
        self._inner = inner
        self._wire = wire
        self._owner = owner

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if data and not self._inner.is_closing():
            self._wire.sent(bytes(data))
        self._inner.write(data)

    def writelines(self, list_of_data: Any) -> None:
        for data in list_of_data:
            self.write(data)

    def write_eof(self) -> None:
        self._inner.write_eof()

    def can_write_eof(self) -> bool:
        return self._inner.can_write_eof()

    def abort(self) -> None:
        self._inner.abort()

    def close(self) -> None:
        self._inner.close()

    def is_closing(self) -> bool:
        return self._inner.is_closing()

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return self._inner.get_extra_info(name, default)

    def pause_reading(self) -> None:
        self._inner.pause_reading()

    def resume_reading(self) -> None:
        self._inner.resume_reading()

    def is_reading(self) -> bool:
        return self._inner.is_reading()

    def set_write_buffer_limits(self, high: int | None = None, low: int | None = None) -> None:
        self._inner.set_write_buffer_limits(high, low)

    def get_write_buffer_size(self) -> int:
        return self._inner.get_write_buffer_size()

    def get_write_buffer_limits(self) -> tuple[int, int]:
        return self._inner.get_write_buffer_limits()

    def set_protocol(self, protocol: asyncio.BaseProtocol) -> None:
        raise NotImplementedError("a tapped connection keeps its protocol")

    def get_protocol(self) -> asyncio.BaseProtocol:
        return self._owner.inner


class _TappedProtocol(asyncio.Protocol):
    """A server connection's protocol, recorded: each chunk is told to the tap, then handed
    to the protocol the server was built with."""

    def __init__(self, inner: asyncio.Protocol, tap: Tap) -> None:
        self.inner = inner
        self._tap = tap
        self._wire: ConnectionTap | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        stream = cast(asyncio.Transport, transport)  # a server's connection: a stream
        self._wire = wire = self._tap.connection(endpoints_of(stream, "tcp", "remote"))
        self.inner.connection_made(_TappedTransport(stream, wire, self))

    def data_received(self, data: bytes) -> None:
        if self._wire is not None:
            self._wire.received(data)
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        if self._wire is not None:
            self._wire.ended(by_peer=True)
            self._wire = None
        return self.inner.eof_received()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._wire is not None:
            self._wire.ended(by_peer=exc is not None)
            self._wire = None
        self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()


#: peers of one tapped UDP server whose recorders are kept; the oldest is let go beyond it,
#: so a flood of datagrams from ever new source ports cannot grow memory
MAX_DATAGRAM_PEERS = 1024


class _TappedDatagramTransport(asyncio.DatagramTransport):
    def __init__(self, inner: asyncio.DatagramTransport, owner: _TappedDatagramProtocol):
        super().__init__()
        self._inner = inner
        self._owner = owner

    def sendto(self, data: bytes | bytearray | memoryview, addr: Any = None) -> None:
        if not self._inner.is_closing():
            self._owner.wire(addr).sent(bytes(data))
        self._inner.sendto(data, addr)

    def abort(self) -> None:
        self._inner.abort()

    def close(self) -> None:
        self._inner.close()

    def is_closing(self) -> bool:
        return self._inner.is_closing()

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return self._inner.get_extra_info(name, default)

    def get_protocol(self) -> asyncio.BaseProtocol:
        return self._owner.inner

    def set_protocol(self, protocol: asyncio.BaseProtocol) -> None:
        raise NotImplementedError("a tapped endpoint keeps its protocol")


class _TappedDatagramProtocol(asyncio.DatagramProtocol):
    """A UDP server endpoint, recorded: one recorder per peer address."""

    def __init__(self, inner: asyncio.DatagramProtocol, tap: Tap) -> None:
        self.inner = inner
        self._tap = tap
        self._transport: asyncio.DatagramTransport | None = None
        #: the transport the wrapped protocol was given (``create_datagram_endpoint`` returns it)
        self.proxy: _TappedDatagramTransport | None = None
        self._wires: OrderedDict[tuple[str, int], ConnectionTap] = OrderedDict()

    def wire(self, addr: Any) -> ConnectionTap:
        key = _address(addr)
        wire = self._wires.get(key)
        if wire is None:
            assert self._transport is not None
            endpoints = endpoints_of(self._transport, "udp", "remote", addr)
            wire = self._wires[key] = self._tap.connection(endpoints)
            if len(self._wires) > MAX_DATAGRAM_PEERS:
                _, oldest = self._wires.popitem(last=False)
                oldest.ended(by_peer=False)
        else:
            self._wires.move_to_end(key)
        return wire

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # a datagram transport, whatever its class says (asyncio's derives from Transport)
        self._transport = cast(asyncio.DatagramTransport, transport)
        self.proxy = _TappedDatagramTransport(self._transport, self)
        self.inner.connection_made(self.proxy)

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.wire(addr).received(data)
        self.inner.datagram_received(data, addr)

    def error_received(self, exc: Exception) -> None:
        self.inner.error_received(exc)

    def connection_lost(self, exc: Exception | None) -> None:
        for wire in self._wires.values():
            wire.ended(by_peer=False)
        self._wires.clear()
        self.inner.connection_lost(exc)


async def create_server(
    factory: Callable[[], asyncio.Protocol], host: str, port: int, **kwargs: Any
) -> asyncio.Server:
    """``loop.create_server``, its connections recorded when a ``capturing`` block is open."""
    loop = asyncio.get_running_loop()
    tap = current_tap()
    if tap is None:
        return await loop.create_server(factory, host, port, **kwargs)
    return await loop.create_server(lambda: _TappedProtocol(factory(), tap), host, port, **kwargs)


async def start_server(
    client_connected_cb: Callable[
        [asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None] | None
    ],
    host: str,
    port: int,
    **kwargs: Any,
) -> asyncio.Server:
    """``asyncio.start_server``, its connections recorded when a ``capturing`` block is open
    (built as asyncio builds it: a ``StreamReaderProtocol`` per connection)."""
    tap = current_tap()
    if tap is None:
        return await asyncio.start_server(client_connected_cb, host, port, **kwargs)
    loop = asyncio.get_running_loop()

    def factory() -> asyncio.Protocol:
        reader = asyncio.StreamReader(loop=loop)
        return asyncio.StreamReaderProtocol(reader, client_connected_cb, loop=loop)

    return await loop.create_server(lambda: _TappedProtocol(factory(), tap), host, port, **kwargs)


async def create_datagram_endpoint(
    factory: Callable[[], asyncio.DatagramProtocol], **kwargs: Any
) -> tuple[asyncio.DatagramTransport, asyncio.DatagramProtocol]:
    """``loop.create_datagram_endpoint``, its datagrams recorded when a ``capturing`` block
    is open. The transport returned is the one the protocol was given."""
    loop = asyncio.get_running_loop()
    tap = current_tap()
    if tap is None:
        return await loop.create_datagram_endpoint(factory, **kwargs)
    _, protocol = await loop.create_datagram_endpoint(
        lambda: _TappedDatagramProtocol(factory(), tap), **kwargs
    )
    assert isinstance(protocol, _TappedDatagramProtocol) and protocol.proxy is not None
    return protocol.proxy, protocol.inner
