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

from plcstack.errors import PlcTimeout
from plcstack.north.layout import JsonLayout
from plcstack.north.mqtt import MqttSettings, MqttSink
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.aio_helpers import eventually
from tests.north_helpers import subscriber
from tests.scan_helpers import scan
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


def _status_scan(plc: str, online: bool, t: float) -> Scan:
    if online:
        return scan(Sample(plc, "x", 1, Quality.GOOD, t, t + 0.01))
    error = f"{plc}: read D0 x1: no answer within 0.2 s"
    return scan(Sample(plc, "x", None, Quality.BAD, t, t + 0.2, error, PlcTimeout))


async def test_every_plcs_retained_status_is_there_again_after_a_broker_restart() -> None:
    """A broker restarted without its retained messages (no persistence, or killed before it
    saved them). Before: only the poller's own status was published again on the reconnect, so
    a late subscriber found no status for any PLC that had not changed since (19 of 21)."""
    online = {f"press{i}": i % 3 != 0 for i in range(7)}
    topics = [f"plcstack/{plc}/status" for plc in online]
    with Mosquitto(persistence=False) as broker:
        groups = {p: ["default"] for p in online}
        layout = JsonLayout("plcstack", "restart-test", groups=groups, plcs=list(online))
        sink = MqttSink(
            MqttSettings(host=broker.host, port=broker.port, reconnect_max=0.2), layout=layout
        )
        await sink.start()
        try:
            await sink.wait_connected(5)
            t = 1_800_000_000.0
            sink.submit([_status_scan(p, up, t + i) for i, (p, up) in enumerate(online.items())])
            await sink.wait_drained(5)
            assert len(await _retained(broker.host, broker.port, topics)) == len(topics)
            broker.restart()  # the retained messages are gone with it
            await eventually(lambda: not sink.connected or sink.stats.connects > 1, "drop seen")
            await sink.wait_connected(10)
            await sink.wait_drained(5)
            retained = await _retained(broker.host, broker.port, topics)
        finally:
            await sink.aclose(drain=0)
    assert {t.split("/")[1]: s["status"] for t, s in retained.items()} == {
        plc: "online" if up else "offline" for plc, up in online.items()
    }
    # each as it was said: the time of the change, not of the reconnect
    assert [retained[t]["timestamp"] for t in topics] == [
        round((1_800_000_000.0 + i) * 1000) + (10 if up else 200)
        for i, up in enumerate(online.values())
    ]
