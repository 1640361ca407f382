"""Health that tells the truth: ``/healthz`` of the metrics endpoint and of the web console
answers 200 only while every part of the run is healthy, and names each one that is not.

Before: ``/healthz`` answered ``ok`` while the broker was down (``plcstack_mqtt_connected`` 0)
and while the audit file could not be written.
"""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import pytest

from plcstack.config import load_config
from plcstack.north import queue_file
from plcstack.north.pipeline import North
from plcstack.north.web.server import WebConsole
from plcstack.poll.engine import Poller
from plcstack.sim import e71 as e71_sim
from tests.aio_helpers import eventually
from tests.disk_helpers import fill, small_disk
from tests.servers import Influxd, Mosquitto
from tests.test_north_metrics import http


async def test_healthz_names_the_broker_and_the_audit_until_they_are_back(
    tmp_path: Path, mosquitto: Mosquitto
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[mqtt]\nurl = "{mosquitto.url}"\nreconnect_max = 0.2\n'
        '[audit]\npath = "/dev/full"\n'  # opens, then every line fails: No space left
        "[web]\nport = 0\n[metrics]\nport = 0\n"
        '[[plc]]\nname = "press1"\nurl = "e71+tcp://127.0.0.1:1"\n'
        '[plc.tags]\nstrokes = { address = "D100" }\n'
    )
    loaded = load_config(path)
    config, north_config = loaded.poll, loaded.north
    mosquitto.stop()  # the broker is away when the run starts
    poller = Poller(config)
    async with poller, North(poller, north_config) as north:
        mqtt, metrics, web = north.mqtt, north.metrics, north.face(WebConsole)
        assert mqtt is not None and metrics is not None and web is not None
        consumer = asyncio.create_task(north.run())  # the dead PLC's scans fill the queue
        await eventually(lambda: mqtt.last_error is not None, "a connection attempt failed")
        await eventually(lambda: len(mqtt.buffer) > 0, "messages wait for the broker")
        north.writes.refuse("web", None, "press1", "strokes", 1, "busy", "test", peer=None)
        down = [
            await http(port, b"GET /healthz HTTP/1.0\r\n\r\n") for port in (metrics.port, web.port)
        ]
        alive = [
            await http(port, b"GET /livez HTTP/1.0\r\n\r\n") for port in (metrics.port, web.port)
        ]
        mosquitto.start()
        await eventually(lambda: mqtt.connected, "the broker is back", timeout=10)
        north.writes.refuse("web", None, "press1", "strokes", 1, "busy", "test", peer=None)
        audit_only = await http(metrics.port, b"GET /healthz HTTP/1.0\r\n\r\n")
        consumer.cancel()
        await asyncio.gather(consumer, return_exceptions=True)
    assert alive == [(200, b"alive\n")] * 2
    for status, body in down:
        assert status == 503
        lines = body.decode().splitlines()
        assert [line.split(":")[0] for line in lines] == ["mqtt", "audit"], lines
        assert f"MQTT broker {mosquitto.url}: connect: nothing listens there" in lines[0]
        assert " since 20" in lines[0] and " messages waiting" in lines[0]
        assert lines[1].startswith("audit: cannot write /dev/full (No space left on device)")
        assert lines[1].endswith("1 lines not written")
    status, body = audit_only
    assert status == 503 and body.decode().splitlines()[0].startswith("audit: cannot write")
    assert len(body.decode().splitlines()) == 1  # the broker is healthy again: not named


async def test_healthz_is_200_with_every_part_named_while_all_is_well(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[audit]\npath = "{tmp_path / "writes.jsonl"}"\n[metrics]\nport = 0\n'
        '[[plc]]\nname = "press1"\nurl = "e71+tcp://127.0.0.1:1"\n'
        '[plc.tags]\nstrokes = { address = "D100" }\n'
    )
    loaded = load_config(path)
    config, north_config = loaded.poll, loaded.north
    poller = Poller(config)
    async with poller, North(poller, north_config) as north:
        assert north.metrics is not None
        healthy = await http(north.metrics.port, b"GET /healthz HTTP/1.0\r\n\r\n")
    stopped = [h.line() for h in north.health() if not h.ok]
    assert healthy == (200, b"ok\npoller: ok\nmetrics: ok\naudit: ok, 0 lines not written\n")
    # after the run: the poller is not running, and no face is listening
    assert stopped == ["poller: the poller is not running", "metrics: not listening on 127.0.0.1:0"]


async def test_healthz_names_influxdb_while_it_cannot_be_written_to(
    tmp_path: Path, influxd: Influxd
) -> None:
    """The Influx writer is a face like the others: its outage in /healthz, named, with the
    lines that wait; healthy again once InfluxDB takes writes."""
    influxd.create_database("plant")
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[influx]\nurl = "{influxd.url}"\ndatabase = "plant"\nbatch_wait = "50ms"\n'
        'reconnect_max = "200ms"\n[metrics]\nlisten = "127.0.0.1:0"\n'
        '[[plc]]\nname = "press1"\nurl = "e71+tcp://127.0.0.1:1"\n'
        '[plc.tags]\nstrokes = { address = "D100" }\n'
    )
    loaded = load_config(path)
    influxd.stop()
    poller = Poller(loaded.poll)
    async with poller, North(poller, loaded.north) as north:
        metrics = north.metrics
        assert metrics is not None
        consumer = asyncio.create_task(north.run())  # the dead PLC's scans are lines too
        await eventually(
            lambda: any(h.name == "influx" and not h.ok for h in north.health()),
            "the writer found InfluxDB away",
        )
        down = await http(metrics.port, b"GET /healthz HTTP/1.0\r\n\r\n")
        influxd.start()
        await eventually(
            lambda: all(h.ok for h in north.health() if h.name == "influx"),
            "InfluxDB takes writes again",
            timeout=10,
        )
        up = await http(metrics.port, b"GET /healthz HTTP/1.0\r\n\r\n")
        consumer.cancel()
        await asyncio.gather(consumer, return_exceptions=True)
    status, body = down
    assert status == 503
    (line,) = body.decode().splitlines()
    assert line.startswith(f"influx: InfluxDB at {influxd.url} cannot be written to:"), line
    assert "connection refused" in line and " since 20" in line, line
    assert line.endswith(" lines waiting"), line
    status, body = up
    assert status == 200 and "\ninflux: ok, " in body.decode(), body


async def healthz(*ports: int) -> list[tuple[int, bytes]]:
    return [await http(port, b"GET /healthz HTTP/1.0\r\n\r\n") for port in ports]


async def livez(*ports: int) -> list[tuple[int, bytes]]:
    return [await http(port, b"GET /livez HTTP/1.0\r\n\r\n") for port in ports]


async def test_healthz_names_full_disks_under_the_queue_and_the_audit_until_they_have_room(
    tmp_path: Path, mosquitto: Mosquitto, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A live PLC, the broker away, the disk under ``buffer_path`` and the one under the audit
    full (two 256 KiB tmpfs): ``/healthz`` of the metrics endpoint and of the console is 503,
    naming the broker (why, since when, messages waiting), the queue's file (full, messages
    lost) and the audit file; with room on both disks and the broker back it is 200 again.
    ``/livez`` is 200 throughout."""
    # a disk that took writes again counts as recovered after this long without a refusal
    monkeypatch.setattr(queue_file, "SETTLE_SECONDS", 0.2)
    with small_disk(tmp_path / "queue") as queue, small_disk(tmp_path / "audit") as audit:
        async with await e71_sim.start() as sim:
            path = tmp_path / "plant.toml"
            path.write_text(
                f'[poll]\ninterval = 0.02\n[mqtt]\nurl = "{mosquitto.url}"\nreconnect_max = 0.2\n'
                f'buffer_path = "{queue / "q.sqlite"}"\nbuffer_memory = 0\n'
                f'[audit]\npath = "{audit / "writes.jsonl"}"\n'
                "[web]\nport = 0\n[metrics]\nport = 0\n"
                f'[[plc]]\nname = "press1"\nurl = "{sim.url}"\n'
                '[plc.tags]\nstrokes = { address = "D100" }\n'
            )
            loaded = load_config(path)
            mosquitto.stop()
            async with Poller(loaded.poll) as poller, North(poller, loaded.north) as north:
                mqtt, metrics, web = north.mqtt, north.metrics, north.face(WebConsole)
                assert mqtt is not None and metrics is not None and web is not None
                ports = (metrics.port, web.port)
                consumer = asyncio.create_task(north.run())
                try:
                    await eventually(lambda: len(mqtt.buffer) > 0, "messages wait on disk")
                    fillers = [fill(queue), fill(audit)]
                    north.writes.refuse("web", None, "press1", "strokes", 1, "busy", "t", peer=None)
                    await eventually(lambda: mqtt.buffer.failure is not None, "the disk is full")
                    down, alive = await healthz(*ports), await livez(*ports)
                    for filler in fillers:
                        filler.unlink()
                    mosquitto.start()
                    await eventually(lambda: mqtt.connected, "the broker is back")
                    north.writes.refuse("web", None, "press1", "strokes", 1, "busy", "t", peer=None)
                    await eventually(
                        lambda: mqtt.buffer.failure is None, "the queue's disk takes writes"
                    )
                    up, alive_again = await healthz(*ports), await livez(*ports)
                finally:
                    consumer.cancel()
                    await asyncio.gather(consumer, return_exceptions=True)
    assert alive == alive_again == [(200, b"alive\n")] * 2
    for status, body in down:
        assert status == 503
        lines = body.decode().splitlines()
        assert [line.split(":")[0] for line in lines] == ["mqtt", "audit"], lines
        # each problem with its own since when; the figures of the part at the end
        broker, disk_full = lines[0].split("; store-and-forward file ")
        assert broker.startswith(f"mqtt: MQTT broker {mosquitto.url}: connect: nothing listens")
        assert re.search(r"\) since 20\S+Z \(\d+ s ago\)$", broker), broker
        assert re.fullmatch(
            rf"{re.escape(str(queue / 'q.sqlite'))} cannot be written \(database or disk is full\),"
            r" \d+ messages lost since 20\S+Z \(\d+ s ago\), [1-9]\d* messages waiting",
            disk_full,
        ), disk_full
        assert lines[1].startswith(
            f"audit: cannot write {audit / 'writes.jsonl'} (No space left on device)"
        )
    for status, body in up:
        assert status == 200, body
        assert body.decode().splitlines()[0] == "ok"
