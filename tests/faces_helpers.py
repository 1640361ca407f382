"""Helpers of the native-face tests: a poller on one simulated PLC, and raw exchanges that keep
every byte of an answer (to compare a face's answer with the PLC's own, byte for byte)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, suppress
from typing import Any, Protocol

from plcstack.codecs._common import NEED_DATA
from plcstack.poll.config import parse_config
from plcstack.poll.engine import Poller

__all__ = ["RawStream", "polled"]


class _Codec(Protocol):
    def send(self, request: Any) -> bytes: ...

    def receive_data(self, data: bytes) -> None: ...

    def next_event(self) -> Any: ...


@asynccontextmanager
async def polled(url: str, tags: str, *, interval: float = 0.02) -> AsyncIterator[Poller]:
    """A poller of one PLC ``kiln1`` at ``url``; ``tags``: the body of its ``[plc.tags]``."""
    text = f"""
[poll]
interval = {interval}
timeout = 5.0

[[plc]]
name = "kiln1"
url = "{url}"

[plc.tags]
{tags}
"""
    async with Poller(parse_config(text)) as poller:
        yield poller


class RawStream:
    """One TCP connection and a client codec: each :meth:`ask` returns the decoded answer and
    every byte it came in."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, codec: _Codec):
        self.reader = reader
        self.writer = writer
        self.codec = codec

    @classmethod
    async def open(cls, host: str, port: int, codec: _Codec) -> RawStream:
        reader, writer = await asyncio.open_connection(host, port)
        return cls(reader, writer, codec)

    async def ask(self, request: Any, timeout: float = 10.0) -> tuple[Any, bytes]:
        self.writer.write(self.codec.send(request))
        raw = b""
        async with asyncio.timeout(timeout):
            while True:
                chunk = await self.reader.read(65536)
                if not chunk:
                    raise ConnectionError(f"closed after {raw.hex(' ')}")
                raw += chunk
                self.codec.receive_data(chunk)
                event = self.codec.next_event()
                if event is not NEED_DATA:
                    return event, raw

    async def aclose(self) -> None:
        self.writer.close()
        with suppress(ConnectionError, OSError):
            await self.writer.wait_closed()
