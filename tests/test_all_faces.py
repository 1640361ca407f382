"""One ``plcstack poll`` serves every face from one connection per PLC.

An S5-LAN module takes one connection at a time. Before, a plant that wanted OPC UA, MQTT, Modbus
and the web console ran ``plcstack serve opcua`` beside ``plcstack poll``: the second poller's
connection was refused (``an S5-LAN module accepts one connection at a time``), and ``serve
opcua`` with ``[mqtt]``, ``[web]`` and ``[modbus]`` in its file served only OPC UA and metrics.
Now one process serves them all, read by their real clients at once: mosquitto and a subscriber,
asyncua's client, libmodbus, HTTP; writes from OPC UA and the web go through the one write path
and its audit; the simulator counts one connection in all.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import sys
from pathlib import Path

import aiohttp
import pytest
from asyncua import ua
from asyncua.client.client import Client

from plcstack.sim import s5lan
from plcstack.sim.s5memory import S5Memory
from tests.modbus_helpers import modbus
from tests.north_helpers import subscriber
from tests.servers import Mosquitto

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "all-faces-token"
#: what each face says on stderr once it serves (the ports are the kernel's: port 0 asked)
LINES = {
    "metrics": re.compile(r"metrics on (http://127\.0\.0\.1:\d+)/metrics"),
    "web": re.compile(r"web console on (http://127\.0\.0\.1:\d+)/"),
    "opcua": re.compile(r"OPC UA server listening on (opc\.tcp://\S+)"),
    "modbus": re.compile(r"Modbus server listening on (127\.0\.0\.1:\d+)"),
}


async def _lines(stream: asyncio.StreamReader, found: dict[str, str], err: list[str]) -> None:
    while line := (await stream.readline()).decode():
        err.append(line)
        for face, pattern in LINES.items():
            if face not in found and (m := pattern.search(line)):
                found[face] = m.group(1)


def _states(health: str) -> list[str]:
    """Each line of a /healthz report up to its figures: "mqtt: ok" of "mqtt: ok, 1 messages
    waiting"."""
    return [line.split(",")[0] for line in health.splitlines()]


@pytest.mark.slow  # an asyncua server and client, a broker and a poll process: several seconds
async def test_one_poll_serves_mqtt_opcua_modbus_web_metrics_and_audit_from_one_connection(
    tmp_path: Path, mosquitto: Mosquitto
) -> None:
    memory = S5Memory(default_dbs={10: 16})
    memory.write_db_words(10, 0, [1234, 0])
    sim = await s5lan.start(memory)  # max_connections = 1: as the module, one at a time
    config = tmp_path / "plant.toml"
    config.write_text(
        f'[poll]\ninterval = 0.1\n[mqtt]\nurl = "{mosquitto.url}"\n'
        '[opcua]\nlisten = "127.0.0.1:0"\nanonymous = "write"\n'
        '[modbus]\nlisten = "127.0.0.1:0"\n'
        '[web]\nlisten = "127.0.0.1:0"\nwrite_token_env = "PLCSTACK_TEST_TOKEN"\n'
        '[metrics]\nlisten = "127.0.0.1:0"\n[audit]\npath = "writes.jsonl"\n'
        f'[[plc]]\nname = "oven"\nurl = "{sim.url}"\n[plc.tags]\n'
        'temp = { address = "DB10.DW0", type = "int16", modbus = "hr:0" }\n'
        'setpoint = { address = "DB10.DW1", type = "int16", modbus = "hr:1", writable = true }\n'
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PLCSTACK_TEST_TOKEN": TOKEN}
    async with subscriber(mosquitto.host, mosquitto.port, "plcstack/oven/#") as sub:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
            cwd=tmp_path, env=env, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert proc.stderr is not None
        found: dict[str, str] = {}
        err: list[str] = []
        reader = asyncio.create_task(_lines(proc.stderr, found, err))
        try:
            async with asyncio.timeout(30):
                while len(found) < len(LINES):
                    assert proc.returncode is None, "".join(err)
                    await asyncio.sleep(0.05)
            # MQTT: the scan's data message (the broker is a real mosquitto)
            await sub.wait_for(lambda s: any("/data/" in t for t, _ in s.messages))
            data = next(json.loads(p) for t, p in sub.messages if "/data/" in t)
            assert data["values"] == {"temp": 1234, "setpoint": 0}
            # OPC UA: asyncua's client reads, and writes the setpoint through the write path
            async with Client(found["opcua"]) as opcua:
                idx = await opcua.get_namespace_index("urn:plcstack")
                temp = opcua.get_node(f"ns={idx};s=oven.temp")
                assert await temp.read_value() == 1234
                setpoint = opcua.get_node(f"ns={idx};s=oven.setpoint")
                await setpoint.write_value(ua.DataValue(ua.Variant(55, ua.VariantType.Int16)))
            assert memory.read_db_words(10, 1, 1) == [55]
            # Modbus: libmodbus reads the registers of the latest scan
            async with asyncio.timeout(10):
                while await modbus(found["modbus"], "rh", 0, 2) != ["ok 1234 55"]:  # noqa: ASYNC110
                    await asyncio.sleep(0.1)  # until a scan after the write reached the image
            # the web console: REST read, and a write with the token
            async with aiohttp.ClientSession() as http:
                async with http.get(found["web"] + "/api/tags?plc=oven") as r:
                    rows = {row["tag"]: row["value"] for row in await r.json()}
                assert rows["temp"] == 1234
                async with http.post(
                    found["web"] + "/api/plcs/oven/tags/setpoint",
                    json={"value": 66},
                    headers={"Authorization": f"Bearer {TOKEN}"},
                ) as r:
                    assert (r.status, await r.json()) == (200, {"ok": True})
                assert memory.read_db_words(10, 1, 1) == [66]
                # metrics and health: one collector, every face healthy
                async with http.get(found["metrics"] + "/metrics") as r:
                    assert 'plcstack_plc_up{plc="oven"} 1.0' in await r.text()
                async with http.get(found["metrics"] + "/healthz") as r:
                    health = await r.text()
                    assert r.status == 200, health
                async with http.get(found["web"] + "/healthz") as r:
                    # the same report; its figures are of the moment each was asked (a message
                    # of the running poll may be waiting for the broker in one and not the other)
                    assert (r.status, _states(await r.text())) == (200, _states(health))
            proc.send_signal(signal.SIGTERM)
            assert await asyncio.wait_for(proc.wait(), 20) == 0, "".join(err)
            await reader
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            await sim.aclose()
    faces = {line.split(":")[0] for line in health.splitlines()[1:]}
    assert faces == {"poller", "mqtt", "opcua", "modbus", "web console", "metrics", "audit"}
    # one connection for all of it: never two at once, the module's one connection never
    # refused to anybody; a reconnect (a request that timed out on a loaded machine drops the
    # connection, by the clients' one policy) is the poller's, and said
    count, said = sim.connection_count, "".join(err)
    assert (count.peak, sim.refused_connections) == (1, 0), said
    assert count.total == 1 or "PLC oven is offline" in said, (count.total, said)
    audit = [json.loads(line) for line in (tmp_path / "writes.jsonl").read_text().splitlines()]
    assert [(a["source"], a["tag"], a["value"], a["result"]) for a in audit] == [
        ("opcua", "setpoint", 55, "ok"),
        ("web", "setpoint", 66, "ok"),
    ]
    assert "Traceback" not in "".join(err)
