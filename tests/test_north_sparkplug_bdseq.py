"""Sparkplug bdSeq across poller restarts: the state file, and two ``plcstack poll`` processes
against a real mosquitto (the first killed, so the broker publishes its Will)."""

from __future__ import annotations

import asyncio
import json
import logging
import random
import signal
import sys
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from plcstack.north.mqtt import MqttSettings, parse_mqtt
from plcstack.north.sparkplug import SparkplugLayout, metric_value
from plcstack.north.sparkplug_pb import Payload
from plcstack.north.sparkplug_state import BdSeqStore, default_state_path
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.north_helpers import subscriber
from tests.servers import Mosquitto

ROOT = Path(__file__).resolve().parent.parent


def bd_seq_of(payload: bytes) -> int:
    values = [metric_value(m) for m in Payload.FromString(payload).metrics if m.name == "bdSeq"]
    assert len(values) == 1, "exactly one bdSeq metric"
    return int(values[0])


def will_bd_seq(layout: SparkplugLayout) -> int:
    return bd_seq_of(layout.will(0.0)[1])


def layout(state: BdSeqStore | None) -> SparkplugLayout:
    return SparkplugLayout("plant", "edge1", {"p": [("t", "uint16", 1)]}, state=state)


def test_bd_seq_continues_in_a_new_process_and_wraps(tmp_path: Path) -> None:
    path = tmp_path / "state" / "sparkplug.json"  # the directory is created on the first save
    store = BdSeqStore(path, "plant", "edge1")
    first = layout(store)
    assert [will_bd_seq(first) for _ in range(3)] == [0, 1, 2]  # one per CONNECT attempt
    assert json.loads(path.read_text()) == {
        "group_id": "plant",
        "edge_node_id": "edge1",
        "bdSeq": 2,
    }
    # the NBIRTH of the session carries the Will's number
    nbirth = first.births(1.0)[0]
    assert nbirth[0] == "spBv1.0/plant/NBIRTH/edge1" and bd_seq_of(nbirth[1]) == 2
    # "restart": a new layout (new process) reading the same file continues after 2
    assert will_bd_seq(layout(BdSeqStore(path, "plant", "edge1"))) == 3
    # 255 is followed by 0
    store.save(254)
    again = layout(BdSeqStore(path, "plant", "edge1"))
    assert [will_bd_seq(again) for _ in range(3)] == [255, 0, 1]
    assert [p.name for p in path.parent.iterdir()] == ["sparkplug.json"]  # no temporary left


@pytest.mark.parametrize(
    "content",
    [
        b"{not json",
        b"",
        random.Random(1).randbytes(300),  # before: UnicodeDecodeError ended the start
        b'{"group_id": "plant", "edge_node_id": "edge1", "bdSeq": 256}',
        b'{"group_id": "plant", "edge_node_id": "edge1", "bdSeq": "7"}',
        b'{"group_id": "plant", "edge_node_id": "edge1", "bdSeq": true}',
        b'{"bdSeq": 7}',
        b"[7]",
        b'{"group_id": "plant", "edge_node_id": "other", "bdSeq": 7}',  # another node's file
    ],
)
def test_a_corrupt_or_foreign_state_file_starts_at_0_with_a_warning(
    tmp_path: Path, content: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "sparkplug.json"
    path.write_bytes(content)
    with caplog.at_level(logging.WARNING, logger="plcstack.north.sparkplug"):
        fresh = layout(BdSeqStore(path, "plant", "edge1"))
    # moved aside, not overwritten: one WARNING names both paths
    [aside] = tmp_path.glob("sparkplug.corrupt-*.json")
    assert aside.read_bytes() == content
    [warning] = caplog.records
    assert str(path) in warning.getMessage() and str(aside) in warning.getMessage()
    assert will_bd_seq(fresh) == 0
    assert json.loads(path.read_text())["bdSeq"] == 0  # and the file is sound again


def test_a_missing_file_starts_at_0_silently(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="plcstack.north.sparkplug"):
        assert will_bd_seq(layout(BdSeqStore(tmp_path / "none.json", "plant", "edge1"))) == 0
    assert not caplog.records


def test_a_state_file_that_cannot_be_written_warns_once_and_publishing_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("")  # even root cannot create a file below a regular file
    store = BdSeqStore(blocker / "sparkplug.json", "plant", "edge1")
    with caplog.at_level(logging.WARNING, logger="plcstack.north.sparkplug"):
        node = layout(store)
        assert [will_bd_seq(node) for _ in range(3)] == [0, 1, 2]
    assert store.failing
    assert len([r for r in caplog.records if "cannot save" in r.getMessage()]) == 1
    blocker.unlink()  # the disk is back: the next CONNECT saves again, and says so
    with caplog.at_level(logging.WARNING, logger="plcstack.north.sparkplug"):
        assert will_bd_seq(node) == 3
    assert not store.failing and json.loads(store.path.read_text())["bdSeq"] == 3
    assert any("saved to" in r.getMessage() for r in caplog.records)


def test_the_state_path_setting_and_its_default_next_to_the_buffer(tmp_path: Path) -> None:
    assert default_state_path(None) is None
    assert default_state_path("/var/lib/plcstack/mqtt.sqlite") == (
        "/var/lib/plcstack/mqtt.sparkplug.json"
    )
    config = PollConfig(
        (PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("t", "D1"),)),), {"default": 1}
    )
    buffered = parse_mqtt({"mode": "sparkplug", "buffer_path": str(tmp_path / "q.sqlite")})
    state = SparkplugLayout.for_config(buffered, config).state
    assert state is not None and state.path == tmp_path / "q.sparkplug.json"
    explicit = parse_mqtt({"mode": "sparkplug", "state_path": str(tmp_path / "s.json")})
    state = SparkplugLayout.for_config(explicit, config).state
    assert state is not None and state.path == tmp_path / "s.json"
    assert SparkplugLayout.for_config(MqttSettings(mode="sparkplug"), config).state is None


CONFIG = """
[poll]
interval = 0.05
[[plc]]
name = "press1"
url = "{url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16" }}
[mqtt]
url = "mqtt://{host}:{port}"
mode = "sparkplug"
group_id = "plant"
client_id = "edge1"
buffer_path = "{buffer}"
"""


def births_and_deaths(messages: list[tuple[str, bytes]]) -> list[tuple[str, int]]:
    out = []
    for topic, payload in messages:
        kind = topic.split("/")[2]
        if kind in ("NBIRTH", "NDEATH"):
            out.append((kind, bd_seq_of(payload)))
    return list(dict.fromkeys(out))  # at-least-once: a repeated message counts once


async def test_a_restarted_poller_continues_bd_seq_and_the_will_of_a_killed_one_matches(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    memory = MelsecMemory()
    sim = await e71.start(memory)
    config = tmp_path / "plant.toml"
    config.write_text(
        CONFIG.format(
            url=sim.url, host=mosquitto.host, port=mosquitto.port, buffer=tmp_path / "q.sqlite"
        )
    )
    procs: list[Any] = []

    async def poll() -> Any:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
            "--duration", "60", cwd=ROOT, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        procs.append(proc)
        return proc

    try:
        async with subscriber(mosquitto.host, mosquitto.port, "spBv1.0/#") as sub:
            first = await poll()
            await sub.wait_for(lambda s: ("NBIRTH", 0) in births_and_deaths(s.messages), 15)
            await sub.wait_for(lambda s: any("/DDATA/" in t for t, _ in s.messages))
            first.send_signal(signal.SIGKILL)  # no NDEATH of its own: the broker sends the Will
            await first.wait()
            await sub.wait_for(lambda s: ("NDEATH", 0) in births_and_deaths(s.messages))
            second = await poll()
            await sub.wait_for(lambda s: ("NBIRTH", 1) in births_and_deaths(s.messages), 15)
            second.terminate()  # a clean stop says NDEATH itself, with its session's number
            _, stderr = await asyncio.wait_for(second.communicate(), 15)
            assert second.returncode == 0, stderr.decode()
            await sub.wait_for(lambda s: ("NDEATH", 1) in births_and_deaths(s.messages))
        assert births_and_deaths(sub.messages) == [
            ("NBIRTH", 0), ("NDEATH", 0), ("NBIRTH", 1), ("NDEATH", 1),
        ]  # fmt: skip
        state = json.loads((tmp_path / "q.sparkplug.json").read_text())
        assert state == {"group_id": "plant", "edge_node_id": "edge1", "bdSeq": 1}
        # the Will is not retained (Sparkplug 3.0): a host subscribing now sees no stale NDEATH.
        # The broker answers each SUBSCRIBE with its retained messages in order, so once the
        # retained marker of the second subscription arrived, any retained NDEATH would have too.
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as client:
            await client.publish("marker/retained", b"m", qos=1, retain=True)
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as late:
            await late.subscribe("spBv1.0/plant/NDEATH/#", qos=1)
            await late.subscribe("marker/retained", qos=1)
            async with asyncio.timeout(5):
                async for message in late.messages:
                    assert str(message.topic) == "marker/retained", "a retained NDEATH"
                    break
    finally:
        for proc in procs:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        await sim.aclose()
