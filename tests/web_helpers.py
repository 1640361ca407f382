"""A running web console over a real E71 simulator, for the REST and the browser tests.

Three PLCs polled every 0.1 s: ``press1`` (an E71 simulator: a writable ``int16`` setpoint, a
float32 temperature with unit and description, a read-only counter), a PLC whose name is a
``<script>`` element (the same simulator; its tag name is one too) and ``dead`` (a closed port).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import struct
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from plcstack import values as vt
from plcstack.north.audit import AuditSettings
from plcstack.north.config import NorthConfig
from plcstack.north.history import HistorySettings
from plcstack.north.pipeline import North
from plcstack.north.web.server import WebConsole
from plcstack.north.web.settings import WebSettings
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.sim import e71 as e71_sim
from plcstack.sim.melsec_memory import MelsecMemory
from tests.servers import free_port

__all__ = ["HOSTILE", "TOKEN", "TOKEN_ENV", "Console", "float_words", "running_console"]

TOKEN_ENV = "PLCSTACK_TEST_WEB_TOKEN"
TOKEN = "s3cret-token"
HOSTILE = "<script>window.pwned=1</script>"


@dataclass
class Console:
    memory: MelsecMemory
    poller: Poller
    web: WebConsole

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.web.port}"


def float_words(value: float) -> list[int]:
    """A float32 as the two words of an E71 (low word first)."""
    low, high = struct.unpack("<HH", struct.pack("<f", value))
    return [low, high]


def plcs(url: str) -> tuple[PlcConfig, ...]:
    tags = (
        TagConfig(
            "setpoint",
            "D100",
            vt.INT16,
            writable=True,
            unit="rpm",
            description="Spindle speed setpoint",
        ),
        TagConfig("temp", "D102", vt.FLOAT32, unit="°C", description="Oil temperature"),
        TagConfig("counter", "D104", vt.INT16),
    )
    hostile = (TagConfig(HOSTILE, "D200", vt.INT16, writable=True),)
    dead = f"e71+tcp://127.0.0.1:{free_port()}?timeout=0.2"
    return (
        PlcConfig("press1", url, tags),
        PlcConfig(HOSTILE, url, hostile),
        PlcConfig("dead", dead, (TagConfig("x", "D0"),), connect_timeout=0.2, backoff_max=0.5),
    )


@contextlib.asynccontextmanager
async def running_console(
    *,
    token: str | None = TOKEN,
    trend_seconds: int = 300,
    audit: Path | None = None,
    history: Path | None = None,
) -> AsyncIterator[Console]:
    """The simulator, the poller, the north side with the console on a free port (and the
    embedded history in the file ``history``, if given)."""
    memory = MelsecMemory()
    memory.write_words("D", 100, [1500])
    memory.write_words("D", 200, [7])
    memory.write_words("D", 102, float_words(61.5))
    sim = await e71_sim.start(memory)
    before = os.environ.get(TOKEN_ENV)
    if token is None:
        os.environ.pop(TOKEN_ENV, None)
    else:
        os.environ[TOKEN_ENV] = token
    try:
        config = PollConfig(plcs(sim.url), {"default": 0.1})
        settings = WebSettings(port=0, write_token_env=TOKEN_ENV, trend_seconds=trend_seconds)
        north_config = NorthConfig(
            web=settings,
            audit=None if audit is None else AuditSettings(str(audit)),
            history=None if history is None else HistorySettings(path=history),
        )
        async with Poller(config) as poller, North(poller, north_config) as north:
            consumer = asyncio.create_task(north.run())
            try:
                assert north.web is not None
                yield Console(memory, poller, north.web)
            finally:
                consumer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await consumer
    finally:
        if before is None:
            os.environ.pop(TOKEN_ENV, None)
        else:
            os.environ[TOKEN_ENV] = before
        await sim.aclose()
