"""Every protocol client against its simulator under uvloop: one write, one read back.

uvloop's transports are not ``asyncio.Transport`` subclasses and it times ``call_at`` with 1 ms
resolution, so code that passes under the default loop can still fail there (the E71 simulator
did: main 3f7aacb). Skipped only when uvloop cannot be imported (it is in the ``dev`` extra).
"""

from __future__ import annotations

import asyncio
import importlib
from typing import Any

import pytest

import plcstack
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.sim.s5memory import S5Memory

uvloop = pytest.importorskip("uvloop")

WORDS = [0, 1, 0x1234, 0x8000, 0xFFFF, 0x1010, 0x0010, 0x1000]  # 0x10 bytes: AS511 DLE stuffing

# (id, simulator module, simulator keyword arguments, memory kind, extra URL query, address);
# the simulator's URL already carries what the client needs (e.g. ``?mk=1``)
CASES: list[tuple[str, str, dict[str, Any], str, str, str]] = [
    ("e71+tcp", "plcstack.sim.e71", {}, "melsec", "", "D100"),
    ("e71+udp", "plcstack.sim.e71", {"transport": "udp"}, "melsec", "", "D100"),
    ("s5lan", "plcstack.sim.s5lan", {}, "s5", "", "DB10.DW3"),
    ("fetchwrite", "plcstack.sim.fetchwrite", {}, "s5", "", "DB10.DW3"),
    ("fetchwrite+mk", "plcstack.sim.fetchwrite", {"mk": True}, "s5", "", "DB10.DW3"),
    ("as511+tcp", "plcstack.sim.as511", {}, "s5", "", "DB10.DW3"),
]


async def _write_then_read(sim_module: str, kwargs: dict[str, Any], memory_kind: str,
                           query: str, address: str) -> list[int]:  # fmt: skip
    memory: Any = MelsecMemory() if memory_kind == "melsec" else S5Memory(default_dbs={10: 64})
    sim = await importlib.import_module(sim_module).start(memory, **kwargs)
    try:
        url = sim.url + (("&" if "?" in sim.url else "?") + query if query else "")
        async with plcstack.connect(url, timeout=5.0) as plc:
            await plc.write(address, WORDS)
            got = await plc.read(address, len(WORDS))
            assert type(asyncio.get_running_loop()).__module__.startswith("uvloop")
            return [int(v) for v in got]
    finally:
        await sim.aclose()


@pytest.mark.parametrize(
    ("sim_module", "kwargs", "memory_kind", "query", "address"),
    [pytest.param(*case[1:], id=case[0]) for case in CASES],
)
def test_write_and_read_back_under_uvloop(
    sim_module: str, kwargs: dict[str, Any], memory_kind: str, query: str, address: str
) -> None:
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        got = runner.run(
            asyncio.wait_for(
                _write_then_read(sim_module, kwargs, memory_kind, query, address), timeout=30
            )
        )
    assert got == WORDS
