"""What each face's clients see of a reload, with the real clients: mosquitto and a subscriber
(JSON status, Sparkplug B births and deaths), asyncua's client (nodes gone and appearing, a
subscription on an unchanged PLC going on).

Before, a changed file changed nothing until a restart, and a restart cost every Sparkplug
device its birth and every OPC UA client its session and subscriptions.
"""

from __future__ import annotations

import asyncio
import itertools
import json
from pathlib import Path
from typing import Any

import pytest
from asyncua.client.client import Client
from asyncua.ua.status_codes import StatusCodes
from asyncua.ua.uaerrors import UaStatusCodeError

from plcstack.north.opcua import OpcUaServer
from plcstack.north.sparkplug_pb import Payload
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.aio_helpers import eventually
from tests.north_helpers import subscriber
from tests.servers import Mosquitto
from tests.test_reload import _file, _plc, running, sims


async def test_json_mqtt_says_a_removed_plc_offline_and_takes_an_added_one(
    tmp_path: Path, mosquitto: Mosquitto
) -> None:
    path = tmp_path / "plant.toml"
    # a prefix of its own: the broker keeps the retained statuses of every other test
    mqtt = f'[mqtt]\nurl = "{mosquitto.url}"\nclient_id = "reload-json"\nprefix = "reload-json"\n'
    async with (
        sims(3) as (a, b, c),
        subscriber(
            mosquitto.host, mosquitto.port, "reload-json/+/status", "reload-json-sub"
        ) as sub,
    ):
        path.write_text(_file(_plc("a", a.url), _plc("b", b.url), head=mqtt))
        async with running(path) as run:

            def status(plc: str) -> list[str]:
                # QoS 1 is at least once: a status the broker delivered again (the same topic
                # and bytes, its time too) is one status (seen under load: "a" online twice)
                topic = f"reload-json/{plc}/status"
                said = dict.fromkeys(sub.messages)
                return [json.loads(p)["status"] for t, p in said if t == topic]

            await sub.wait_for(lambda s: status("a") == ["online"] and status("b") == ["online"])
            path.write_text(_file(_plc("a", a.url), _plc("c", c.url), head=mqtt))
            outcome = await run.control.reload(who="SIGHUP")
            assert outcome.summary == "PLCs added: c; removed: b; changed: none"
            await sub.wait_for(lambda s: status("b") == ["online", "offline"])
            await sub.wait_for(lambda s: status("c") == ["online"])
            assert status("a") == ["online"]  # unchanged: said once
            assert run.poller.stats["a"].reconnects == 0


def _kind(topic: str) -> str:
    return topic.split("/")[2]


def _metrics(payload: bytes) -> list[str]:
    return [m.name for m in Payload.FromString(payload).metrics]


async def test_sparkplug_kills_a_removed_device_births_an_added_one_and_no_node_birth_again(
    tmp_path: Path, mosquitto: Mosquitto
) -> None:
    path = tmp_path / "plant.toml"
    mqtt = (
        f'[mqtt]\nurl = "{mosquitto.url}"\nmode = "sparkplug"\ngroup_id = "reload-spb"\n'
        'client_id = "edge"\n'
    )
    async with (
        sims(4) as (a, b, c, d),
        subscriber(mosquitto.host, mosquitto.port, "spBv1.0/reload-spb/#", "reload-spb-sub") as sub,
    ):
        plcs = [_plc("a", a.url), _plc("b", b.url), _plc("d", d.url)]
        path.write_text(_file(*plcs, head=mqtt))
        async with running(path) as run:

            def seen(kind: str, plc: str | None = None) -> list[bytes]:
                return [
                    p
                    for t, p in sub.messages
                    if _kind(t) == kind and (plc is None or t.endswith(f"/{plc}"))
                ]

            await sub.wait_for(lambda s: len(seen("DDATA", "a")) >= 2 and seen("DDATA", "d"))
            mark = len(sub.messages)
            # b removed, c added, d's tags changed, a unchanged
            d_tags = ('x = "D100"', 'y = "D200"')
            path.write_text(
                _file(_plc("a", a.url), _plc("c", c.url), _plc("d", d.url, *d_tags), head=mqtt)
            )
            outcome = await run.control.reload(who="SIGHUP")
            assert outcome.summary == "PLCs added: c; removed: b; changed: d"

            def after() -> list[tuple[str, str]]:
                return [(_kind(t), t.rsplit("/", 1)[-1]) for t, _ in sub.messages[mark:]]

            await sub.wait_for(
                lambda s: ("DDATA", "c") in after() and after().count(("DDATA", "d")) >= 1
            )
            await sub.wait_for(lambda s: after().count(("DDATA", "a")) >= 2)
            births = [x for x in after() if x[0] in ("NBIRTH", "DBIRTH", "DDEATH", "NDEATH")]
            assert sorted(births) == [
                ("DBIRTH", "c"),
                ("DBIRTH", "d"),
                ("DDEATH", "b"),
                ("DDEATH", "d"),
            ], after()
            assert after().index(("DDEATH", "d")) < after().index(("DBIRTH", "d"))
            death_b = after().index(("DDEATH", "b"))  # data queued before it may precede it
            assert ("DDATA", "b") not in after()[death_b:]
            # the new birth declares the new metrics; nothing before c's birth
            birth_d = [p for t, p in sub.messages[mark:] if t.endswith("/DBIRTH/edge/d")]
            assert sorted(_metrics(birth_d[0])) == ["x", "y"]
            assert after().index(("DBIRTH", "c")) < after().index(("DDATA", "c"))
            # sequence numbers go on in the same session (no NBIRTH resets them)
            seqs = [Payload.FromString(p).seq for t, p in sub.messages if "NDEATH" not in t]
            assert all((y - x) % 256 == 1 for x, y in itertools.pairwise(seqs)), seqs


@pytest.mark.slow  # an asyncua server and client: a few seconds on a loaded machine
async def test_opcua_nodes_of_a_removed_plc_go_an_added_plcs_appear_subscriptions_go_on(
    tmp_path: Path,
) -> None:
    path = tmp_path / "plant.toml"
    opcua = '[opcua]\nlisten = "127.0.0.1:0"\n'
    memory = MelsecMemory()
    memory.write_words("D", 100, [7])
    a = await e71.start(memory)
    async with sims(2) as (b, c):
        try:
            path.write_text(_file(_plc("a", a.url), _plc("b", b.url), head=opcua))
            async with running(path) as run:
                server = run.north.face(OpcUaServer)
                assert server is not None
                async with Client(server.url) as client:
                    idx = await client.get_namespace_index("urn:plcstack")
                    node = client.get_node(f"ns={idx};s=a.x")
                    heard: list[Any] = []

                    class Handler:
                        def datachange_notification(self, _: Any, value: Any, __: Any) -> None:
                            heard.append(value)

                    sub = await client.create_subscription(20, Handler())
                    await sub.subscribe_data_change(node)
                    await eventually(lambda: 7 in heard, "a.x = 7 heard")
                    b_x = client.get_node(f"ns={idx};s=b.x")
                    await eventually_value(b_x, 0)
                    path.write_text(_file(_plc("a", a.url), _plc("c", c.url), head=opcua))
                    outcome = await run.control.reload(who="SIGHUP")
                    assert outcome.summary == "PLCs added: c; removed: b; changed: none"
                    with pytest.raises(UaStatusCodeError) as gone:
                        await b_x.read_value()
                    assert gone.value.code == StatusCodes.BadNodeIdUnknown
                    await eventually_value(client.get_node(f"ns={idx};s=c.x"), 0)
                    # the subscription made before the reload still hears a's changes
                    memory.write_words("D", 100, [8])
                    await eventually(lambda: 8 in heard, "a.x = 8 heard after the reload")
                    await sub.delete()
        finally:
            await a.aclose()


async def eventually_value(node: Any, value: Any) -> None:
    async with asyncio.timeout(5):
        while True:
            try:
                if await node.read_value() == value:
                    return
            except UaStatusCodeError:
                pass  # no value yet
            await asyncio.sleep(0.05)


async def test_modbus_registers_of_a_removed_plc_go_and_an_added_ones_appear(
    tmp_path: Path,
) -> None:
    """libmodbus reads: the registers of an unchanged PLC keep their value through the
    reload, a removed PLC's answer 0x02 (unmapped), an added PLC's read once it was scanned."""
    from plcstack.north.modbus.server import ModbusServer
    from tests.modbus_helpers import modbus

    path = tmp_path / "plant.toml"
    face = '[modbus]\nlisten = "127.0.0.1:0"\n'
    memories = [MelsecMemory() for _ in range(3)]
    for i, memory in enumerate(memories):
        memory.write_words("D", 100, [100 + i])
    started = [await e71.start(memory) for memory in memories]
    a, b, c = started
    try:
        path.write_text(
            _file(
                _plc("a", a.url, 'x = { address = "D100", modbus = "hr:0" }'),
                _plc("b", b.url, 'x = { address = "D100", modbus = "hr:1" }'),
                head=face,
            )
        )
        async with running(path) as run:
            server = run.north.face(ModbusServer)
            assert server is not None
            endpoint = f"127.0.0.1:{server.port}"
            async with asyncio.timeout(10):  # until b's first scan reached the image
                while await modbus(endpoint, "rh", 0, 2) != ["ok 100 101"]:  # noqa: ASYNC110
                    await asyncio.sleep(0.05)
            path.write_text(
                _file(
                    _plc("a", a.url, 'x = { address = "D100", modbus = "hr:0" }'),
                    _plc("c", c.url, 'x = { address = "D100", modbus = "hr:2" }'),
                    head=face,
                )
            )
            outcome = await run.control.reload(who="SIGHUP")
            assert outcome.summary == "PLCs added: c; removed: b; changed: none"
            # at once: a's register kept its value, b's is gone
            assert await modbus(endpoint, "rh", 0, 1, "rh", 1, 1) == ["ok 100", "exc 0x02"]
            async with asyncio.timeout(10):  # until c's first scan reached the image
                while await modbus(endpoint, "rh", 2, 1) != ["ok 102"]:  # noqa: ASYNC110
                    await asyncio.sleep(0.05)
            assert run.north.face(ModbusServer) is server  # the same server, clients kept
    finally:
        for sim in started:
            await sim.aclose()


async def test_web_console_rows_of_a_removed_plc_go_and_an_added_ones_appear(
    tmp_path: Path,
) -> None:
    """GET /api/plcs and a tag read over HTTP: after the reload the removed PLC is unknown, the
    added one is listed, the unchanged one kept its value and its console (no restart)."""
    import aiohttp

    from plcstack.north.web.server import WebConsole

    path = tmp_path / "plant.toml"
    face = '[web]\nlisten = "127.0.0.1:0"\n'
    async with sims(3) as (a, b, c):
        path.write_text(_file(_plc("a", a.url), _plc("b", b.url), head=face))
        async with running(path) as run, aiohttp.ClientSession() as http:
            console = run.north.face(WebConsole)
            assert console is not None
            url = console.url.rstrip("/")

            async def plcs() -> list[str]:
                async with http.get(f"{url}/api/plcs") as r:
                    return sorted(row["name"] for row in await r.json())

            async def tags(plc: str) -> list[str]:
                async with http.get(f"{url}/api/tags?plc={plc}") as r:
                    return [row["tag"] for row in await r.json()]

            assert await plcs() == ["a", "b"]
            async with asyncio.timeout(10):
                while await tags("a") != ["x"]:  # noqa: ASYNC110 - until a's first sample
                    await asyncio.sleep(0.02)
            path.write_text(_file(_plc("a", a.url), _plc("c", c.url), head=face))
            outcome = await run.control.reload(who="SIGHUP")
            assert outcome.summary == "PLCs added: c; removed: b; changed: none"
            assert await plcs() == ["a", "c"]
            async with http.get(f"{url}/api/tags?plc=b") as r:
                assert r.status == 404, await r.text()
            assert await tags("a") == ["x"]  # kept through the reload
            assert run.north.face(WebConsole) is console
