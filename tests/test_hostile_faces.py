"""64 idle sockets from one host against every kind of listening face that speaks a PLC
protocol: the gateway's S5-LAN, FETCH/WRITE, E71 and AS511 faces and the simulators of every
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

from plcstack.clients import connect
from plcstack.errors import PlcError
from plcstack.gateway.faces import FaceSettings, PlcFaces
from plcstack.sim import as511, e71, fetchwrite, s5lan
from plcstack.sim.base import Simulator, TcpSimulator
from plcstack.transports.guard import TOTALS, Limits
from tests.aio_helpers import eventually
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

    if kind.startswith("gateway-"):
        protocol = kind.removeprefix("gateway-")
        plc: Simulator
        if protocol == "e71":
            plc = await e71.start()
        elif protocol == "as511":
            plc = await as511.start()
        else:
            plc = await s5lan.start()
        cap = {"s5lan": 8, "fetchwrite": 16, "e71": 32, "as511": 1}[protocol]
        limits = Limits(cap, first_request_timeout=FIRST)
        settings = FaceSettings(protocol, "127.0.0.1", 0, "kiln1", limits=limits)  # type: ignore[arg-type]
        client = connect(plc.url)
        try:
            async with PlcFaces("kiln1", client, [settings]) as faces:
                (server,) = faces.servers
                assert isinstance(server, TcpSimulator)
                family = protocol if protocol in ("e71", "as511") else "s5"
                yield server, server.url, ADDRESS[family]
        finally:
            await client.aclose()
            await plc.aclose()
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


#: every kind of face :func:`face` starts
KINDS = [
    "gateway-s5lan",
    "gateway-fetchwrite",
    "gateway-e71",
    "gateway-as511",
    "sim-e71",
    "sim-s5lan",
    "sim-fetchwrite",
    "sim-as511",
]


@pytest.mark.parametrize("kind", KINDS)
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


#: bytes that are no request of the face's protocol: an undefined E71 subheader (answered 50H),
#: an S5-LAN block with a wrong header length, a FETCH/WRITE job without its "S5"
GARBAGE = {"e71": bytes([0x65]) + bytes(11), "s5lan": bytes(26), "fetchwrite": bytes(16)}


@pytest.mark.parametrize("kind", [k for k in KINDS if not k.endswith("as511")])  # AS511: no garbage
async def test_one_clients_garbage_is_said_once_per_burst(
    kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: the faces took garbage without a word (an S5-LAN or FETCH/WRITE face closed the
    connection, an E71 answered its end code): nothing told an operator that a client spoke
    another protocol. After: the first, naming the client, and the count of the rest."""
    caplog.set_level(logging.WARNING)
    protocol = kind.split("-", 1)[1]
    sent = 20
    async with face(kind) as (server, _, _):
        for _ in range(sent):
            reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
            writer.write(GARBAGE[protocol])
            await asyncio.wait_for(reader.read(100), 5)  # the face's answer, or its close
            writer.close()
        await eventually(lambda: server.guard.counts["malformed"] == sent, "all garbage seen")
    lines = guard_lines(caplog, "127.0.0.1")
    lines = [line for line in lines if "malformed" in line or "sent a" in line]
    assert len(lines) == 2, lines
    assert "127.0.0.1:" in lines[0] and "sent a malformed" in lines[0]
    assert f"{sent - 1} more malformed requests from 127.0.0.1" in lines[1]
