"""Partner side of E71 fixed buffer communication (spec §8), on its own connection.

A fixed buffer is bound to one E71 connection (its own local port, §1.1, App. A), so this client
talks to that port: ``E71FixedBufferClient.from_url("e71+tcp://10.0.0.5:1281?code=ascii")``
(``?procedure=0`` for "without procedure"). Both directions run over the one connection:

* :meth:`E71FixedBufferClient.send` sends a telegram to the PLC and returns once the E71 answered
  ``E0 00`` — which it does only after the PLC program took the data (§8.1). Another end code
  raises :class:`PlcErrorResponse` (50H/52H/54H of seed Tab. 7-2); no answer within the timeout
  raises :class:`PlcTimeout` and closes the connection (the PLC may or may not have the data).
  Never retried.
* :meth:`E71FixedBufferClient.messages` is an async iterator over telegrams the PLC sends; each is
  acknowledged with ``E0 00`` as it is handed to the caller.
* Without procedure there is no header and no answer: :meth:`send_raw` / :meth:`messages` move raw
  byte chunks (at most 2046 bytes, §8.2).

:class:`E71BroadcastReceiver` receives the UDP broadcasts an E71 sends without procedure (§8.3).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator, Sequence
from typing import Any, Self

from plcstack.clients.base import (
    DEFAULT_CONNECT_TIMEOUT,
    DEFAULT_TIMEOUT,
    Client,
    Points,
    as_points,
)
from plcstack.clients.e71 import client_code
from plcstack.clients.options import COMMON, choice, flag
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.e71 import Code
from plcstack.codecs.e71_buffers import (
    FIXED_BUFFER_END_CODES,
    FixedBufferAck,
    FixedBufferConnection,
    FixedBufferData,
    FixedBufferError,
    RawBufferConnection,
)
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    LocalProtocolError,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.resource import AsyncResource
from plcstack.transports import ip_transport
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.transports.udp import UdpTransport
from plcstack.url import PlcUrl

__all__ = ["E71BroadcastReceiver", "E71FixedBufferClient", "Message"]

#: a telegram's words (with procedure) or a raw chunk (without)
Message = tuple[int, ...] | bytes

_END = object()
#: messages received and not yet taken by ``receive`` before the reader stops reading (without
#: procedure the PLC sends at will; a consumer that falls behind must not cost memory)
INBOX_MAX = 64


class E71FixedBufferClient(Client):
    """One fixed-buffer connection to an E71 (with or without procedure, TCP or UDP)."""

    OPTIONS = (
        *COMMON,
        choice("code", "binary", ("binary", "ascii"), "must match DIP switch SW2 (§11.4)"),
        flag("procedure", True, "fixed buffer with procedure (handshake) or without"),
    )

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        code: Code | str = Code.BINARY,
        procedure: bool = True,
        timeout: float = DEFAULT_TIMEOUT,
        connect_timeout: float = DEFAULT_CONNECT_TIMEOUT,
        backoff: Backoff | None = None,
    ) -> None:
        super().__init__(
            name, transport, timeout=timeout, connect_timeout=connect_timeout, backoff=backoff
        )
        self.code = client_code(code, name)
        if not procedure and self.code is Code.ASCII:
            raise AddressError("without procedure the data are always binary (§8.2)", plc=name)
        self.procedure = procedure
        self._udp = isinstance(transport, UdpTransport)
        self.codec: FixedBufferConnection | RawBufferConnection = self._new_codec()
        self._inbox: asyncio.Queue[Message | object] = asyncio.Queue()
        #: set when a message was taken from a full inbox (the reader waits for it)
        self._space = asyncio.Event()
        self._ack: asyncio.Future[int] | None = None
        self._reader: asyncio.Task[None] | None = None

    @classmethod
    def create(cls, url: PlcUrl, options: dict[str, Any]) -> Self:
        transport = ip_transport(url.host, url.port, url.transport)
        return cls(url.raw, transport, **options)

    def _new_codec(self) -> FixedBufferConnection | RawBufferConnection:
        if self.procedure:
            return FixedBufferConnection(self.code, transport="udp" if self._udp else "tcp")
        return RawBufferConnection()

    # -- connection life cycle: a reader task per connection ---------------------------------------
    def connection_made(self) -> None:
        self.codec = self._new_codec()
        self._reader = asyncio.get_running_loop().create_task(self._read_loop(self.codec))

    async def aclose(self) -> None:
        await super().aclose()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader
        self._inbox.put_nowait(_END)

    async def _read_loop(self, codec: FixedBufferConnection | RawBufferConnection) -> None:
        try:
            while True:
                # Flow control: with INBOX_MAX messages nobody took yet, stop reading; the
                # transport's bounded queue then pauses the socket and TCP stops the PLC.
                while self._inbox.qsize() >= INBOX_MAX:
                    self._space.clear()
                    await self._space.wait()
                codec.receive_data(await self.transport.read())
                while (event := codec.next_event()) is not NEED_DATA:
                    self._dispatch(event)
        except (PlcError, ValueError) as exc:
            if codec is self.codec:  # a reader of an already replaced connection stays quiet
                self._broken(exc)

    def _dispatch(self, event: FixedBufferData | FixedBufferAck | FixedBufferError | bytes) -> None:
        if self.unproven:
            self.answered()  # the PLC talks: the reconnect backoff starts over
        if isinstance(event, FixedBufferAck):
            if self._ack is not None and not self._ack.done():
                self._ack.set_result(event.end_code)
        elif isinstance(event, FixedBufferData):
            self._inbox.put_nowait(event.values)
        elif isinstance(event, bytes):
            self._inbox.put_nowait(event)
        else:  # pragma: no cover - the partner role raises instead
            raise RemoteProtocolError(event.reason)

    def _broken(self, exc: BaseException) -> None:
        error = exc if isinstance(exc, PlcError) else RemoteProtocolError(str(exc))
        if self._ack is not None and not self._ack.done():
            # A send is waiting: it gets its own (unbound) error so that its message names the
            # send, not "receive", and says that the outcome is unknown.
            kind = ConnectionLost if isinstance(error, ConnectionLost) else RemoteProtocolError
            self._ack.set_exception(
                kind(f"{error.message}; the PLC may or may not have taken the data")
            )
        error.bind(plc=self.name, request="receive")
        self._inbox.put_nowait(error)
        self.transport.abort()

    # -- partner -> PLC -------------------------------------------------------------------------
    async def send(self, values: Sequence[int]) -> None:
        """Send one telegram (1-1017 words, ASCII 1-508) and wait until the PLC took it."""
        what = f"fixed buffer send x{len(values)}"
        if not self.procedure:
            raise AddressError("without procedure use send_raw(bytes)", plc=self.name, request=what)
        words = []
        for v in values:
            if isinstance(v, bool) or not isinstance(v, int) or not -0x8000 <= v <= 0xFFFF:
                raise AddressError(f"word value {v!r} invalid", plc=self.name, request=what)
            words.append(v & 0xFFFF)
        async with self._lock:
            await self._ensure_open(what)
            codec = self.codec
            assert isinstance(codec, FixedBufferConnection)
            try:
                data = codec.send_data(words)
            except LocalProtocolError as exc:
                raise AddressError(exc.message, plc=self.name, request=what) from None
            self._ack = asyncio.get_running_loop().create_future()
            self.stats.requests += 1
            try:
                self.transport.write(data)
                async with asyncio.timeout(self.timeout):
                    end = await self._ack
            except asyncio.CancelledError:
                # The caller gave up: the answer may still come and must not confirm the next
                # telegram, and the codec must not keep waiting for it (every later send was
                # refused as "not answered yet"). A new connection settles both.
                self.transport.abort()
                raise
            except TimeoutError:
                self.stats.timeouts += 1
                self.stats.errors += 1
                self.transport.abort()
                raise PlcTimeout(
                    f"no answer within {self.timeout:g} s, connection closed; the PLC may or may "
                    "not have taken the data",
                    plc=self.name,
                    request=what,
                ) from None
            except PlcError as exc:
                self.stats.errors += 1
                raise exc.bind(plc=self.name, request=what) from None
            finally:
                self._ack = None
        if end != 0:
            self.stats.errors += 1
            raise PlcErrorResponse(
                end,
                FIXED_BUFFER_END_CODES.get(end, "undocumented end code"),
                plc=self.name,
                request=what,
            )

    async def send_raw(self, data: bytes) -> None:
        """Without procedure: send 1-2046 bytes; there is no answer (§8.2)."""
        what = f"fixed buffer send {len(data)} bytes"
        if self.procedure:
            raise AddressError("with procedure use send(words)", plc=self.name, request=what)
        try:
            payload = RawBufferConnection().send(data)
        except LocalProtocolError as exc:
            raise AddressError(exc.message, plc=self.name, request=what) from None
        async with self._lock:
            await self._ensure_open(what)
            self.stats.requests += 1
            self.transport.write(payload)

    # -- PLC -> partner -------------------------------------------------------------------------
    async def receive(self, timeout: float | None = None) -> Message:
        """The next message the PLC sent (acknowledged with ``E0 00`` when returned)."""
        if not self.transport.is_open:
            async with self._lock:
                await self._ensure_open("receive")
        try:
            async with asyncio.timeout(timeout):
                item = await self._inbox.get()
            self._space.set()
        except TimeoutError:
            raise PlcTimeout(
                f"no fixed-buffer message within {timeout:g} s", plc=self.name, request="receive"
            ) from None
        if item is _END:
            raise ConnectionLost("client is closed", plc=self.name, request="receive")
        if isinstance(item, PlcError):
            raise item
        assert isinstance(item, (tuple, bytes))
        if self.procedure and self.transport.is_open:
            codec = self.codec
            assert isinstance(codec, FixedBufferConnection)
            self.transport.write(codec.send_ack(0))
            # telegrams that arrived meanwhile were held by the codec until this answer
            while (event := codec.next_event()) is not NEED_DATA:
                self._dispatch(event)
        return item

    async def messages(self) -> AsyncIterator[Message]:
        """Messages the PLC sends, until the client is closed; reconnects as needed."""
        while True:
            try:
                yield await self.receive()
            except ConnectionLost:
                if self._closed:
                    return
                raise

    # -- the generic Client API -----------------------------------------------------------------
    async def read(self, address: str = "", count: int = 1) -> list[int]:
        """The next PLC message's words (``address`` is ignored; ``count`` must match)."""
        item = await self.receive()
        values = list(item)
        if count != len(values):
            raise RemoteProtocolError(
                f"message of {len(values)} words, expected {count}", plc=self.name, request="read"
            )
        return values

    async def write(self, address: str, values: Points) -> None:
        """Send ``values`` as one telegram (``address`` is ignored)."""
        await self.send([int(v) for v in as_points(values, plc=self.name, request="send")])


class E71BroadcastReceiver(AsyncResource):
    """Receives UDP broadcasts an E71 sends without procedure (partner IP FFFFFFFFH, §8.3).

    ``async with E71BroadcastReceiver(port) as rx: async for data, (ip, port) in rx: ...``.
    Datagrams are not filtered: receivers must check the contents themselves (§8.3).

    ``host`` defaults to ``127.0.0.1``: binding every interface makes a process answerable to
    the whole network, so receiving real broadcasts is an explicit ``host="0.0.0.0"``. At most
    ``max_queued`` datagrams wait for :meth:`receive`; further ones are dropped and counted in
    :attr:`dropped` (anyone on the segment can send broadcasts, faster than we take them).
    """

    def __init__(self, port: int, host: str = "127.0.0.1", *, max_queued: int = 1024) -> None:
        if max_queued < 1:
            raise AddressError("max_queued must be at least 1")
        self.host = host
        self.port = port
        self._queue: asyncio.Queue[tuple[bytes, tuple[str, int]]] = asyncio.Queue(max_queued)
        self._transport: asyncio.DatagramTransport | None = None
        #: datagrams dropped because ``max_queued`` were waiting
        self.dropped = 0

    async def aopen(self) -> None:
        """Bind the port (``port=0``: a free one, then in :attr:`port`)."""
        loop = asyncio.get_running_loop()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        sock.bind((self.host, self.port))
        self.port = sock.getsockname()[1]
        queue = self._queue
        receiver = self

        class _Rx(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
                if queue.full():
                    receiver.dropped += 1
                    return
                queue.put_nowait((data, (str(addr[0]), int(addr[1]))))

        transport, _ = await loop.create_datagram_endpoint(_Rx, sock=sock)
        self._transport = transport

    async def aclose(self) -> None:
        if self._transport is not None:
            self._transport.close()

    async def receive(self, timeout: float | None = None) -> tuple[bytes, tuple[str, int]]:
        try:
            async with asyncio.timeout(timeout):
                return await self._queue.get()
        except TimeoutError:
            raise PlcTimeout(
                f"no broadcast on port {self.port} within {timeout:g} s", request="receive"
            ) from None

    def __aiter__(self) -> AsyncIterator[tuple[bytes, tuple[str, int]]]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[tuple[bytes, tuple[str, int]]]:
        while True:
            yield await self.receive()
