"""64 idle sockets from one host against every kind of listening face that speaks a PLC
protocol: the gateway's S5-LAN, FETCH/WRITE and E71 faces and the simulators of every
protocol. A legitimate client is served within the first-request deadline (at once where the
per-host cap leaves it a slot), the refusals are counted, and the log says them once when they
begin and once with their count.

Before: the gateway's S5-LAN face served 8 sockets for up to 600 s each (renewable by
reconnecting), refused every other client ("peer closed the connection"), logged nothing at the
default level and counted no refusal; the E71 simulator the same with its 8 connections.
"""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

import pytest

from plcstack import gateway
from plcstack.clients import connect
from plcstack.clients.share import SharedConnection
from plcstack.errors import PlcError
from plcstack.gateway import e71server
from plcstack.gateway.e71face import E71Executor
from plcstack.sim import as511, e71, fetchwrite, s5lan
from plcstack.sim.base import TcpSimulator
from plcstack.transports.guard import TOTALS, Limits
from tests.aio_helpers import eventually
from tests.faces_helpers import polled
from tests.guard_helpers import ATTACKER, IDLE_SOCKETS, guard_lines, idle_sockets

#: seconds a socket may stay silent after connecting, in these tests
FIRST = 1.0

#: a read each face answers, in its PLC's notation
ADDRESS = {"s5": "DB1.DW0", "e71": "D0", "as511": "MB0"}


@asynccontextmanager
async def face(kind: str) -> AsyncIterator[tuple[TcpSimulator, str, str]]:
    """The face of ``kind`` (first-request deadline :data:`FIRST`), the URL a client uses,
    and the address it reads."""

    def module(n: int) -> Limits:  # a simulated module: n connections from any host
        return Limits(n, n, first_request_timeout=FIRST)

    if kind in ("gateway-s5lan", "gateway-fetchwrite"):
        plc = await s5lan.start()
        gw = await gateway.start(
            plc.url,
            s5lan=("127.0.0.1", 0),
            fetchwrite=("127.0.0.1", 0),
            s5lan_limits=Limits(8, first_request_timeout=FIRST),
            fetchwrite_limits=Limits(16, first_request_timeout=FIRST),
        )
        server = gw.s5lan if kind == "gateway-s5lan" else gw.fetchwrite
        assert server is not None
        try:
            yield server, server.url, ADDRESS["s5"]
        finally:
            await gw.aclose()
            await plc.aclose()
    elif kind == "gateway-e71":
        melsec = await e71.start()
        try:
            async with polled(melsec.url, 'x = "D0"') as poller:
                share = SharedConnection(poller.client("kiln1"), name="kiln1")
                async with share:
                    executor = E71Executor(share)
                    e71face = await e71server.start(
                        executor, limits=Limits(32, first_request_timeout=FIRST)
                    )
                    assert isinstance(e71face, e71server.E71TcpFace)
                    async with e71face:
                        yield e71face, e71face.url, ADDRESS["e71"]
        finally:
            await melsec.aclose()
    else:
        sims: dict[str, Callable[[], object]] = {
            "sim-e71": lambda: e71.start(limits=module(8)),
            "sim-s5lan": lambda: s5lan.start(limits=module(1)),
            "sim-fetchwrite": lambda: fetchwrite.start(limits=module(16)),
            "sim-as511": lambda: as511.start(limits=module(16)),
        }
        sim = await sims[kind]()  # type: ignore[misc]
        assert isinstance(sim, TcpSimulator)
        async with sim:
            family = kind.removeprefix("sim-")
            yield sim, sim.url, ADDRESS.get(family, ADDRESS["s5"])


async def served(url: str, address: str, within: float) -> float:
    """Seconds until a client of ``url`` (on 127.0.0.1) got an answer to a read of
    ``address``, trying again while it is turned away; fails after ``within`` seconds."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    async with asyncio.timeout(within):
        while True:
            try:
                async with connect(url, timeout=1.0, connect_timeout=1.0) as plc:
                    await plc.read(address)
                    return loop.time() - start
            except PlcError:
                await asyncio.sleep(0.05)  # refused: all slots are taken for now


@pytest.mark.parametrize(
    "kind",
    [
        "gateway-s5lan",
        "gateway-fetchwrite",
        "gateway-e71",
        "sim-e71",
        "sim-s5lan",
        "sim-fetchwrite",
        "sim-as511",
    ],
)
async def test_64_idle_sockets_lock_no_client_out(
    kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    async with face(kind) as (server, url, address):
        guard = server.guard
        limits = guard.limits
        assert limits.max_clients is not None and limits.max_clients_per_host is not None
        before = TOTALS.get(guard.face, "max_clients_per_host") + TOTALS.get(
            guard.face, "max_clients"
        )
        async with idle_sockets(server.port):
            counts = guard.counts
            await eventually(
                lambda: (
                    guard.refused + guard.hosts[ATTACKER] + counts["first_request_timeout"]
                    == IDLE_SOCKETS
                ),
                "every socket refused or holding a slot",
            )
            # a per-host cap below the face's cap leaves the others a slot at once; a module
            # that does not tell hosts apart frees its slots at the first-request deadline
            took = await served(url, address, within=FIRST + 5.0)
            print(f"{kind}: {guard.refused} refused; a legitimate client served in {took:.2f} s")
            if limits.max_clients_per_host < limits.max_clients:
                assert guard.counts["first_request_timeout"] == 0  # served before any closed
            await eventually(lambda: not guard.hosts[ATTACKER], "the silent sockets closed")
        refused = guard.refused
        assert refused >= IDLE_SOCKETS - limits.max_clients_per_host
        assert guard.counts["first_request_timeout"] >= 1
        after = TOTALS.get(guard.face, "max_clients_per_host") + TOTALS.get(
            guard.face, "max_clients"
        )
        assert after - before == refused  # what /metrics serves
    # the refusals of the attacker: once when they began, once with the count of the rest
    # (a module's refusals of the legitimate client while it waited are said apart)
    lines = guard_lines(caplog)
    refusals = [line for line in lines if "refus" in line]
    assert len(refusals) == 2, lines
    assert f"refusing {ATTACKER}:" in refusals[0]
    more = re.search(rf"(\d+) more connections of {ATTACKER} refused", refusals[1])
    assert more is not None and int(more.group(1)) + 1 <= refused, refusals
    if limits.max_clients_per_host < limits.max_clients:
        assert int(more.group(1)) + 1 == refused
    closes = [line for line in lines if "no complete request within 1 s" in line]
    assert 1 <= len(closes) <= 2 and f"closed the connection of {ATTACKER}:" in closes[0]
