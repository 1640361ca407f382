"""Shared tools of the robustness tests: a loop-error recorder, capture of real request frames, and
a scriptable TCP proxy that misbehaves on purpose between a client and a simulator."""

from __future__ import annotations

import asyncio
import gc
import logging
import os
import random
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass, field
from typing import Any

from plcstack.clients.as511 import AS511Client
from plcstack.clients.base import Client
from tests.aio_helpers import ends_quietly, eventually

__all__ = [
    "GOOD",
    "LoopErrors",
    "MisbehavingProxy",
    "capture_request",
    "fd_count",
    "giving_up_soon",
    "mutations",
    "record_loop_errors",
]


class LoopErrors:
    """Everything asyncio would have reported as unhandled: exception-handler calls plus ERROR
    log records of ``asyncio`` and ``plcstack`` (e.g. "Exception in callback", "Task exception
    was never retrieved", "Fatal error: protocol.data_received() call failed")."""

    def __init__(self) -> None:
        self.contexts: list[dict[str, Any]] = []
        self.records: list[logging.LogRecord] = []

    def describe(self) -> list[str]:
        out = [str(c.get("message")) + f" {c.get('exception')!r}" for c in self.contexts]
        out += [r.getMessage() for r in self.records]
        return out


class _Collect(logging.Handler):
    def __init__(self, sink: list[logging.LogRecord]) -> None:
        super().__init__(logging.ERROR)
        self.sink = sink

    def emit(self, record: logging.LogRecord) -> None:
        self.sink.append(record)


@asynccontextmanager
async def record_loop_errors() -> AsyncIterator[LoopErrors]:
    loop = asyncio.get_running_loop()
    errors = LoopErrors()
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda _loop, context: errors.contexts.append(context))
    handler = _Collect(errors.records)
    loggers = [logging.getLogger("asyncio"), logging.getLogger("plcstack")]
    for lg in loggers:
        lg.addHandler(handler)
    try:
        yield errors
        # "Task exception was never retrieved" is only reported when the task is collected
        for _ in range(3):
            await asyncio.sleep(0)
        gc.collect()
        await asyncio.sleep(0)
    finally:
        for lg in loggers:
            lg.removeHandler(handler)
        loop.set_exception_handler(previous)


async def capture_request(client: Client, action: Callable[[], Any]) -> bytes:
    """The bytes ``client`` writes while running ``action`` (a real, valid request frame)."""
    sent: list[bytes] = []
    transport = client.transport
    original = transport.write

    def spy(data: bytes) -> None:
        sent.append(bytes(data))
        original(data)

    transport.write = spy  # type: ignore[method-assign]
    try:
        await action()
    finally:
        transport.write = original  # type: ignore[method-assign]
    return b"".join(sent)


def mutations(frame: bytes, rng: random.Random, limit: int) -> list[bytes]:
    """Bad variants of a valid frame: every truncation, 2-byte fields forced to FFFF/0000
    (oversized or zero counts and lengths wherever they sit), single-byte flips; at most
    ``limit``, deterministic for a seeded ``rng``."""
    out = [frame[:k] for k in range(1, len(frame))]
    for i in range(max(len(frame) - 1, 0)):
        out.append(frame[:i] + b"\xff\xff" + frame[i + 2 :])
        out.append(frame[:i] + b"\x00\x00" + frame[i + 2 :])
    for i in range(len(frame)):
        out.append(frame[:i] + bytes([frame[i] ^ (1 << rng.randrange(8))]) + frame[i + 1 :])
    rng.shuffle(out)
    return out[:limit]


#: the deadline of every request a test needs answered: long, because a healthy answer comes at
#: once and waiting costs nothing, while a stall of a loaded machine (100 ms and more) must not
#: fail it. Only the request a peer is meant to leave unanswered gets a short deadline.
GOOD = 5.0


@contextmanager
def giving_up_soon(plc: Client, deadline: float) -> Iterator[None]:
    """Within the block the client gives up after ``deadline`` (AS511: per character too), for
    the one request a mute or late peer never answers, so that the test waits ``deadline`` and
    not ``GOOD``; afterwards the client's own deadlines are back."""
    saved = plc.timeout
    plc.timeout = deadline
    pg = plc.pg if isinstance(plc, AS511Client) else None
    saved_pg = (pg.char_timeout, pg.response_timeout) if pg is not None else None
    if pg is not None:
        pg.char_timeout = pg.response_timeout = deadline / 2
    try:
        yield
    finally:
        plc.timeout = saved
        if pg is not None and saved_pg is not None:
            pg.char_timeout, pg.response_timeout = saved_pg


def fd_count() -> int:
    return len(os.listdir("/proc/self/fd"))


# -- a proxy that misbehaves on purpose --------------------------------------------------------


@dataclass
class Script:
    """What the proxy does with the next upstream answer (mode) and what it saw."""

    #: "pass", "late", "twice", "garbage", "half_close", "mute", "close", "mutate"
    mode: str = "pass"
    #: for "mutate": what the peer sends instead of the real answer
    mutate: Callable[[bytes], bytes] = bytes
    late: float = 0.0
    garbage: bytes = b"\x10\x02garbage\xff\x00\x55" * 3  # longer than any header
    #: requests (client -> proxy chunks) and connections seen
    chunks: list[bytes] = field(default_factory=list)
    connections: int = 0


class MisbehavingProxy:
    """TCP proxy client -> proxy -> simulator. ``script.mode`` applies to answers while set.

    ``upstream_free``, for a simulator that takes one connection at a time (S5-LAN): true once
    it has let go of its connection; each new connection waits for it before connecting
    upstream. A client's close and its next connect reach a real module in order on one path;
    through the proxy they are two independent connections, and the proxy's close of the old
    one (a few loop passes after the client's, and under load delivered by the kernel after a
    later connect) lost the race to the new one often enough to be refused as a second client.
    """

    def __init__(
        self,
        upstream_host: str,
        upstream_port: int,
        *,
        upstream_free: Callable[[], bool] | None = None,
    ) -> None:
        self.upstream = (upstream_host, upstream_port)
        self.upstream_free = upstream_free
        self.script = Script()
        self.server: asyncio.Server | None = None
        self.port = 0
        self._tasks: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self) -> MisbehavingProxy:
        self.server = await asyncio.start_server(ends_quietly(self._handle), "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    @property
    def requests(self) -> int:
        return len(self.script.chunks)

    async def aclose(self) -> None:
        assert self.server is not None
        self.server.close()
        for w in list(self._writers):
            w.transport.abort()
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.server.wait_closed()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.script.connections += 1
        self._writers.add(writer)
        if self.upstream_free is not None:
            await eventually(self.upstream_free, "the simulator let go of its last connection", 5)
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.upstream)
        except OSError:
            writer.transport.abort()
            return
        self._writers.add(up_writer)

        async def client_to_sim() -> None:
            while data := await reader.read(65536):
                self.script.chunks.append(data)
                up_writer.write(data)
            up_writer.close()

        async def sim_to_client() -> None:
            while data := await up_reader.read(65536):
                await self._answer(data, writer)
            writer.close()

        tasks = [asyncio.ensure_future(client_to_sim()), asyncio.ensure_future(sim_to_client())]
        for t in tasks:
            self._tasks.add(t)
            t.add_done_callback(self._tasks.discard)
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            await asyncio.sleep(0.05)
        except asyncio.CancelledError:
            pass
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            writer.transport.abort()
            up_writer.transport.abort()
            self._writers.discard(writer)
            self._writers.discard(up_writer)

    async def _answer(self, data: bytes, writer: asyncio.StreamWriter) -> None:
        s = self.script
        if s.mode == "pass":
            writer.write(data)
        elif s.mode == "late":
            await asyncio.sleep(s.late)
            if not writer.is_closing():
                writer.write(data)
        elif s.mode == "twice":
            writer.write(data + data)
        elif s.mode == "garbage":
            writer.write(s.garbage)
        elif s.mode == "half_close":
            writer.write(data[: max(1, len(data) // 2)])
            await writer.drain()
            writer.transport.abort()
        elif s.mode == "close":
            writer.transport.abort()
        elif s.mode == "mutate":
            writer.write(s.mutate(data))
        # "mute": drop it
