"""``plcstack poll`` with [mqtt] and [report]: samples reach the broker once, writes come back."""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

import aiomqtt

from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.north_helpers import subscriber
from tests.servers import Mosquitto

ROOT = Path(__file__).resolve().parent.parent


async def test_poll_cli_publishes_by_exception_and_takes_writes(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    memory = MelsecMemory()
    memory.write_words("D", 100, [7])
    sim = await e71.start(memory)
    config = tmp_path / "plant.toml"
    config.write_text(
        f"""
[poll]
interval = 0.05
[[plc]]
name = "press1"
url = "{sim.url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16", writable = true }}
[mqtt]
url = "mqtt://{mosquitto.host}:{mosquitto.port}"
client_id = "cli-test"
buffer_path = "{tmp_path / "queue.sqlite"}"
[report]
max_silence = 3600
"""
    )
    proc = None
    try:
        async with subscriber(mosquitto.host, mosquitto.port, "plcstack/#") as sub:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
                "--duration", "30", cwd=ROOT, stderr=asyncio.subprocess.PIPE,
            )  # fmt: skip
            await sub.wait_for(lambda s: any("/data/" in t for t, _ in s.messages), timeout=15)
            async with aiomqtt.Client(mosquitto.host, mosquitto.port) as client:
                request = {"id": "w1", "tag": "strokes", "value": 8}
                await client.publish("plcstack/press1/write/req", json.dumps(request), qos=1)
                await sub.wait_for(lambda s: any("/write/resp" in t for t, _ in s.messages))
                await sub.wait_for(
                    lambda s: sum("/data/" in t for t, _ in s.messages) >= 2, timeout=10
                )
            await asyncio.sleep(0.3)  # a few more scans of an unchanged value: not reported
            proc.terminate()
            _, stderr = await asyncio.wait_for(proc.communicate(), 15)
            await sub.wait_for(
                lambda s: any("_poller" in t and b"offline" in p for t, p in s.messages)
            )
    finally:
        if proc is not None and proc.returncode is None:
            proc.kill()
        await sim.aclose()
    assert proc.returncode == 0, stderr.decode()
    reply = next(json.loads(p) for t, p in sub.messages if t.endswith("/write/resp"))
    assert reply == {"id": "w1", "ok": True}
    assert memory.read_words("D", 100, 1) == [8]
    data = [json.loads(p) for t, p in sub.messages if t == "plcstack/press1/data/default"]
    assert [d["values"] for d in data] == [{"strokes": 7}, {"strokes": 8}]  # by exception
    statuses = [json.loads(p)["status"] for t, p in sub.messages if "_poller" in t]
    assert statuses == ["online", "offline"]
