"""``plcstack serve modbus``: the command, its /metrics (requests, exceptions by code, clients),
the write audit (source ``modbus``),
requests pipelined on one connection, a broken frame closing the connection, overlaps exit 2."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import struct
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from plcstack.cli import main
from plcstack.cli.serve_modbus import run_modbus
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.modbus_helpers import modbus
from tests.servers import free_port

CONFIG = """
[poll]
interval = 0.05
[modbus]
listen = "127.0.0.1:0"
[audit]
path = "writes.jsonl"
[[plc]]
name = "press1"
url = "{url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16", modbus = "hr:0", writable = true }}
[[plc]]
name = "dead"
url = "e71+tcp://127.0.0.1:{dead}?timeout=0.2"
[plc.tags]
level = {{ address = "D1", type = "uint16", modbus = "hr:1" }}
"""


async def get(port: int, path: str) -> str:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.0\r\n\r\n".encode())
    data = await reader.read()
    writer.close()
    return data.partition(b"\r\n\r\n")[2].decode()


async def listening(serving: asyncio.Task[int], capsys: pytest.CaptureFixture[str]) -> str:
    """The endpoint of the ``listening on`` line ``serve modbus`` prints on stderr (the command
    must not end before it)."""
    async with asyncio.timeout(20):
        err = ""
        while "Modbus server listening on " not in err:
            assert not serving.done(), serving.result()
            await asyncio.sleep(0.01)
            err += capsys.readouterr().err
    return err.split("Modbus server listening on ", 1)[1].split()[0]


def mbap(transaction: int, pdu: bytes, protocol: int = 0) -> bytes:
    return struct.pack(">HHHB", transaction, protocol, len(pdu) + 1, 1) + pdu


async def test_serve_modbus_answers_and_counts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    memory = MelsecMemory()
    memory.write_words("D", 100, [5])
    sim = await e71.start(memory)
    path = tmp_path / "plant.toml"
    path.write_text(CONFIG.format(url=sim.url, dead=free_port()))
    metrics = free_port()
    args = argparse.Namespace(config=str(path), duration=None, metrics_port=metrics)
    serving = asyncio.create_task(run_modbus(args))
    try:
        endpoint = await listening(serving, capsys)
        # the line comes once every PLC's first scan is stored: the first read has the value
        assert await modbus(endpoint, "rh", 0, 1) == ["ok 5"]
        # the dead PLC's tag; nothing mapped; the dead tag and an unmapped register (0x02 wins)
        assert (
            await modbus(endpoint, "rh", 1, 1, "rh", 7, 1, "rh", 1, 2)
            == ["exc 0x0B"] + ["exc 0x02"] * 2
        )

        # writes: one confirmed, one refused (read-only); both in the audit with source modbus
        assert await modbus(endpoint, "wh", 0, 9, "wh", 1, 3) == ["ok", "exc 0x02"]
        assert memory.read_words("D", 100, 1) == [9]
        audit = [json.loads(line) for line in (tmp_path / "writes.jsonl").read_text().splitlines()]
        assert [(a["source"], a["plc"], a["tag"], a["value"], a["result"]) for a in audit] == [
            ("modbus", "press1", "strokes", 9, "ok"),
            ("modbus", "dead", "level", 3, "not_writable"),
        ]
        assert audit[0]["previous"] == 5
        # the register shows the written value from the next scan on (interval 0.05 s); until
        # then it holds the last scan's 5
        async with asyncio.timeout(10):
            for _ in range(1000):
                if await modbus(endpoint, "rh", 0, 1) == ["ok 9"]:
                    break
                await asyncio.sleep(0.01)
            else:
                raise AssertionError("the written 9 never reached register 0")

        host, port = endpoint.rsplit(":", 1)
        reader, writer = await asyncio.open_connection(host, int(port))
        # two requests in one segment: two answers, in order, on the same connection
        writer.write(mbap(1, bytes.fromhex("0300000001")) + mbap(2, bytes.fromhex("07")))
        first = await reader.readexactly(11)
        second = await reader.readexactly(9)
        assert first == struct.pack(">HHHBBBH", 1, 0, 5, 1, 3, 2, 9)
        assert second == struct.pack(">HHHBBB", 2, 0, 3, 1, 0x87, 0x01)

        text = await get(metrics, "/metrics")
        families = {f.name: f for f in text_string_to_metric_families(text)}
        assert families["plcstack_modbus_clients"].samples[0].value == 1  # the raw connection
        requests = {
            s.labels["function"]: s.value for s in families["plcstack_modbus_requests"].samples
        }
        assert requests["3"] >= 5 and requests["7"] == 1
        exceptions = {
            s.labels["code"]: s.value for s in families["plcstack_modbus_exceptions"].samples
        }
        # 0x0B also answered the reads made before the first poll arrived
        assert exceptions["0x01"] == 1 and exceptions["0x02"] == 3 and exceptions["0x0B"] >= 1
        assert "plcstack_plc_up" in families  # the poller's own metrics, as for plcstack poll

        # a frame that is not Modbus TCP (protocol id 1) ends the connection
        writer.write(mbap(3, bytes.fromhex("0300000001"), protocol=1))
        assert await reader.read() == b""
        writer.close()

        os.kill(os.getpid(), signal.SIGTERM)  # the command's own handler: a clean stop
        assert await asyncio.wait_for(serving, 15) == 0
    finally:
        if not serving.done():
            serving.cancel()
            await asyncio.gather(serving, return_exceptions=True)
        await sim.aclose()


def test_overlapping_map_exits_2_naming_both_tags(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "overlap.toml"
    path.write_text(
        '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\n'
        'x = { address = "D0", type = "int32", modbus = "hr:0" }\n'
        'y = { address = "D2", type = "int16", modbus = "hr:1" }\n'
    )
    assert main(["serve", "modbus", str(path)]) == 2
    err = capsys.readouterr().err
    assert "tag 'y'" in err and "tag 'x'" in err and f"{path}:6" in err and f"{path}:5" in err


async def test_the_listening_line_comes_once_every_plcs_first_scan_is_stored(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A script waits for the line and reads at once: it gets values, not exception 0x0B
    ("waiting for initial data"). The live PLC's first scan is due 0.5 s after the start (the
    first scans are spread over the interval), the dead one's fails at once."""
    memory = MelsecMemory()
    memory.write_words("D", 100, [5])
    sim = await e71.start(memory)
    path = tmp_path / "plant.toml"
    path.write_text(
        f"""
[poll]
interval = 2
[modbus]
listen = "127.0.0.1:0"
[[plc]]
name = "dead"
url = "e71+tcp://127.0.0.1:{free_port()}?timeout=0.2"
[plc.tags]
level = {{ address = "D1", type = "uint16", modbus = "hr:1" }}
[[plc]]
name = "press1"
url = "{sim.url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16", modbus = "hr:0" }}
"""
    )
    args = argparse.Namespace(config=str(path), duration=None, metrics_port=None)
    serving = asyncio.create_task(run_modbus(args))
    try:
        endpoint = await listening(serving, capsys)
        assert await modbus(endpoint, "rh", 0, 1, "rh", 1, 1) == ["ok 5", "exc 0x0B"]
    finally:
        serving.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await serving
        await sim.aclose()
