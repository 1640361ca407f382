"""A running web console over a real E71 simulator, for the REST and the browser tests.

Three PLCs polled every 0.1 s: ``press1`` (an E71 simulator: a writable ``int16`` setpoint, a
float32 temperature with unit and description, a read-only counter, and one tag of each display
form: a ``kh`` word, a ``bool`` with labels, an integer state, a float with decimals), a PLC
whose name is a ``<script>`` element (the same simulator; its tag name is one too) and ``dead``
(a closed port).
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
from plcstack.north.trace import TraceSettings
from plcstack.north.web.server import WebConsole
from plcstack.north.web.settings import DEFAULT_LIMITS, WebSettings
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.sim import e71 as e71_sim
from plcstack.sim.base import Simulator
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.transports.guard import Limits
from tests.servers import free_port

__all__ = ["HOSTILE", "TOKEN", "TOKEN_ENV", "Console", "float_words", "running_console"]

TOKEN_ENV = "PLCSTACK_TEST_WEB_TOKEN"
TOKEN = "s3cret-token"
#: a name that runs script if a page does not escape it (with no / + # or dot, so every face
#: can carry it: the name rule of the configuration)
HOSTILE = "<svg onload=pwned=1>"


@dataclass
class Console:
    memory: MelsecMemory
    poller: Poller
    web: WebConsole
    sim: Simulator

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.web.port}"


def float_words(value: float) -> list[int]:
    """A float32 as the two words of an E71 (low word first)."""
    low, high = struct.unpack("<HH", struct.pack("<f", value))
    return [low, high]


def fleet(url: str, n: int) -> tuple[PlcConfig, ...]:
    """``n`` more PLCs, ``plc000``..., one tag each, polled every second, all answered by one
    E71 simulator on UDP (``url``: a module takes 8 TCP connections at most)."""
    tag = (TagConfig("level", "D300", vt.INT16, group="slow", unit="mm"),)
    return tuple(PlcConfig(f"plc{i:03d}", url, tag) for i in range(n))


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
        # display forms: a hex word, a bool with labels, an integer state, fixed decimals
        TagConfig("status", "D106", vt.KH),
        TagConfig("valve", "M0", vt.BOOL, labels=((0, "closed"), (1, "open"))),
        TagConfig("mode", "D108", vt.INT16, labels=((0, "stopped"), (1, "running"))),
        TagConfig("flow", "D110", vt.FLOAT32, unit="m³/h", decimals=1),
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
    more_plcs: int = 0,
    trace: Path | None = None,
    limits: Limits = DEFAULT_LIMITS,
) -> AsyncIterator[Console]:
    """The simulator, the poller, the north side with the console on a free port (and the
    embedded history in the file ``history``, if given; ``more_plcs`` PLCs besides the three,
    see :func:`fleet`; the flight recorder writing into ``trace``, if given); ``limits``: the
    console's ``[web]`` client limits."""
    memory = MelsecMemory()
    memory.write_words("D", 100, [1500])
    memory.write_words("D", 200, [7])
    memory.write_words("D", 102, float_words(61.5))
    memory.write_words("D", 106, [0x12AF])
    memory.write_words("D", 108, [1])
    memory.write_words("D", 110, float_words(12.345))
    memory.write_bits("M", 0, [True])
    sim = await e71_sim.start(memory)
    extra_sims: list[Simulator] = []
    before = os.environ.get(TOKEN_ENV)
    if token is None:
        os.environ.pop(TOKEN_ENV, None)
    else:
        os.environ[TOKEN_ENV] = token
    try:
        more: tuple[PlcConfig, ...] = ()
        if more_plcs:
            udp = await e71_sim.start(memory, transport="udp")
            extra_sims.append(udp)
            more = fleet(udp.url, more_plcs)
        config = PollConfig(plcs(sim.url) + more, {"default": 0.1, "slow": 1.0})
        settings = WebSettings(
            port=0, write_token_env=TOKEN_ENV, trend_seconds=trend_seconds, limits=limits
        )
        north_config = NorthConfig(
            web=settings,
            audit=None if audit is None else AuditSettings(str(audit)),
            history=None if history is None else HistorySettings(path=history),
            trace=None if trace is None else TraceSettings(directory=trace),
        )
        async with Poller(config) as poller, North(poller, north_config) as north:
            consumer = asyncio.create_task(north.run())
            try:
                console = north.face(WebConsole)
                assert console is not None
                yield Console(memory, poller, console, sim)
            finally:
                consumer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await consumer
    finally:
        if before is None:
            os.environ.pop(TOKEN_ENV, None)
        else:
            os.environ[TOKEN_ENV] = before
        for other in extra_sims:
            await other.aclose()
        await sim.aclose()
