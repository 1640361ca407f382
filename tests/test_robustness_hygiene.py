"""Promise 4: resource hygiene. 200 clients opened, used and closed against every simulator leave
no file descriptor and no task behind (counted in /proc/self/fd and asyncio.all_tasks())."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from plcstack.clients import connect
from plcstack.clients.e71_fixed import E71FixedBufferClient
from plcstack.sim import as511 as as511_sim
from plcstack.sim import e71 as e71_sim
from plcstack.sim import fetchwrite as fw_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.sim.e71_fixed import start_fixed_buffer
from plcstack.url import parse_url
from tests.robust_helpers import fd_count, record_loop_errors

CLIENTS = 200
#: The AS511 simulators share the client's event loop, and both AS511 sides judge a byte by
#: when their loop saw it. A stall of that loop (a loaded machine) then looks like a gap of
#: more than the 0.5 s character timeout to either side, as if the other had gone silent.
#: This test is about leaks, not timing: both sides get a character timeout of 2 s.
PATIENT = 2.0

CASES: dict[str, tuple[Callable[[], Awaitable[Any]], str]] = {
    "e71-tcp": (lambda: e71_sim.start(), "D100"),
    "e71-udp": (lambda: e71_sim.start(transport="udp", code="ascii"), "D100"),
    "s5lan": (lambda: s5lan_sim.start(), "MW100"),
    "fetchwrite-raw": (lambda: fw_sim.start(), "MW100"),
    "fetchwrite-mk-write-port-life-ack": (
        lambda: fw_sim.start(mk=True, write_port=0, life_ack=0.5),
        "MW100",
    ),
    "as511-tcp": (lambda: as511_sim.start(char_timeout=PATIENT), "MB10"),
    "as511-pty": (lambda: as511_sim.start_pty(char_timeout=PATIENT), "MB10"),
}
#: what each case's client adds to the simulator's URL
QUERY = {name: f"?char_timeout={PATIENT:g}" for name in CASES if name.startswith("as511")}


def _others() -> set[asyncio.Task[Any]]:
    return {t for t in asyncio.all_tasks() if t is not asyncio.current_task()}


async def _settled(expected_fds: int, expected_tasks: set[asyncio.Task[Any]]) -> None:
    """Closing is asynchronous on the simulator's side: wait (bounded) for it to finish."""
    for _ in range(200):
        if fd_count() == expected_fds and _others() <= expected_tasks:
            break
        await asyncio.sleep(0.01)
    assert fd_count() == expected_fds
    assert _others() - expected_tasks == set()


async def _one(url: str, address: str, k: int) -> None:
    async with connect(url, timeout=2) as plc:
        if k % 2:
            await plc.write(address, [k & 0xFF])
        assert await plc.read(address) == [(k if k % 2 else k - 1) & 0xFF]


@pytest.mark.parametrize("name", sorted(CASES))
async def test_open_close_200_clients_leaks_nothing(name: str) -> None:
    starter, address = CASES[name]
    async with record_loop_errors() as errors:
        fds_before_sim = fd_count()
        tasks_before_sim = _others()
        sim = await starter()
        try:
            fds, tasks = fd_count(), _others()
            url = sim.url + QUERY.get(name, "")
            await _one(url, address, 1)  # warm: lazy imports, first-connection state
            await _settled(fds, tasks)
            for k in range(2, CLIENTS + 2):
                await _one(url, address, k)
            await _settled(fds, tasks)
        finally:
            await sim.aclose()
        await _settled(fds_before_sim, tasks_before_sim)
    assert errors.describe() == []


@pytest.mark.parametrize("transport", ["tcp", "udp"])
async def test_fixed_buffer_clients_leak_nothing(transport: str) -> None:
    async with record_loop_errors() as errors:
        fds_before_sim = fd_count()
        tasks_before_sim = _others()
        sim = await start_fixed_buffer(transport=transport)  # type: ignore[arg-type]
        try:
            fds, tasks = fd_count(), _others()
            for k in range(CLIENTS):
                async with E71FixedBufferClient.from_url(parse_url(sim.url), timeout=2) as fb:
                    send = asyncio.create_task(fb.send([k]))
                    assert await sim.receive(timeout=2) == (k,)
                    await asyncio.wait_for(send, 2)
            await _settled(fds, tasks)
        finally:
            await sim.aclose()
        await _settled(fds_before_sim, tasks_before_sim)
    assert errors.describe() == []
