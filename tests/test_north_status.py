"""MQTT status topics tell the truth: a clean stop takes every PLC's retained status offline,
and the poller's Last Will carries a real timestamp."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

import aiomqtt

from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.north_helpers import subscriber
from tests.servers import Mosquitto

ROOT = Path(__file__).resolve().parent.parent


async def _retained(host: str, port: int, topics: list[str]) -> dict[str, Any]:
    """The retained message of each topic, as a new subscriber gets it."""
    out: dict[str, Any] = {}
    async with aiomqtt.Client(host, port) as client:
        for topic in topics:
            await client.subscribe(topic, qos=1)
        async with asyncio.timeout(5):
            async for m in client.messages:
                assert isinstance(m.payload, bytes)
                out[str(m.topic)] = json.loads(m.payload)
                if len(out) == len(topics):
                    break
    return out


async def _poll(config: Path) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
        "--duration", "60", cwd=ROOT, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip


async def test_a_clean_stop_takes_every_plc_offline_and_the_will_is_dated(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    sims = [await e71.start(MelsecMemory()) for _ in range(2)]
    config = tmp_path / "plant.toml"
    plcs = "".join(
        f'[[plc]]\nname = "press{i}"\nurl = "{sim.url}"\n[plc.tags]\nx = {{ address = "D0" }}\n'
        for i, sim in enumerate(sims)
    )
    config.write_text(
        f"[poll]\ninterval = 0.05\n{plcs}[mqtt]\n"
        f'url = "mqtt://{mosquitto.host}:{mosquitto.port}"\nclient_id = "status-test"\n'
    )
    statuses = ["plcstack/press0/status", "plcstack/press1/status"]
    poller_topic = "plcstack/_poller/status-test/status"
    try:
        async with subscriber(mosquitto.host, mosquitto.port, "plcstack/+/status") as sub:
            proc = await _poll(config)
            await sub.wait_for(lambda s: {t for t, _ in s.messages} >= set(statuses), 15)
            proc.send_signal(signal.SIGTERM)
            _, err = await asyncio.wait_for(proc.communicate(), 20)
            assert proc.returncode == 0, err.decode()
        retained = await _retained(mosquitto.host, mosquitto.port, [*statuses, poller_topic])
        # main: both PLCs stayed "online" for ever after the poller had stopped
        assert {t: p["status"] for t, p in retained.items()} == {
            statuses[0]: "offline",
            statuses[1]: "offline",
            poller_topic: "offline",
        }

        # a crash: the broker publishes the Will, whose timestamp is a real time (main: 0)
        before = time.time()
        proc = await _poll(config)
        async with subscriber(mosquitto.host, mosquitto.port, poller_topic, "will-sub") as sub:
            await sub.wait_for(
                lambda s: any(json.loads(p)["status"] == "online" for _, p in s.messages), 15
            )
            proc.kill()
            await asyncio.wait_for(proc.communicate(), 20)
            await sub.wait_for(lambda s: json.loads(s.messages[-1][1])["status"] == "offline", 15)
        will = json.loads(sub.messages[-1][1])
        assert will["timestamp"] >= int(before * 1000) - 1000
    finally:
        for sim in sims:
            await sim.aclose()
