"""The Modbus TCP server against an independent client (libmodbus): every function code, word
order, exception answers, a dead PLC, writes confirmed by a simulated E71."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import struct
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from plcstack import ConfigError, load_config
from plcstack.north.audit import Audit, AuditSettings
from plcstack.north.modbus.server import ModbusServer
from plcstack.north.writes import WritePath
from plcstack.poll.config import parse_poll_config
from plcstack.poll.engine import Poller
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.modbus_helpers import modbus
from tests.runtime_helpers import fed
from tests.servers import free_port

PLANT = """
[poll]
interval = 0.05
[modbus]
listen = "127.0.0.1:0"
word_order = "{order}"
[[plc]]
name = "press1"
url = "{url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16", modbus = "hr:0", writable = true }}
temp = {{ address = "D102", type = "float32", modbus = "hr:1", writable = true }}
total = {{ address = "D104", type = "int32", modbus = "hr:3" }}
label = {{ address = "D110", type = "string:4", modbus = "hr:10", writable = true }}
level = {{ address = "D120", type = "int16", scale = [0, 1000, 0.0, 100.0], modbus = "hr:20" }}
code = {{ address = "D130", type = "bcd16", modbus = "hr:30", writable = true }}
pair = {{ address = "D140", type = "int16", count = 2, modbus = "hr:40", writable = true }}
fixed = {{ address = "D150", type = "int16", modbus = "ir:0" }}
alarms = {{ address = "M0", type = "bool", count = 8, modbus = "di:0" }}
valve = {{ address = "M10", type = "bool", modbus = "co:0", writable = true }}
pumps = {{ address = "M20", type = "bool", count = 4, modbus = "co:1", writable = true }}
door = {{ address = "M30", type = "bool", modbus = "co:5" }}
unmapped = "D160"
[[plc]]
name = "dead"
url = "e71+tcp://127.0.0.1:{dead}?timeout=0.2"
[plc.tags]
level = {{ address = "D1", type = "uint16", modbus = "ir:5" }}
setpoint = {{ address = "D2", type = "uint16", modbus = "hr:60", writable = true }}
"""


@dataclass
class Plant:
    memory: MelsecMemory
    poller: Poller
    server: ModbusServer

    @property
    def endpoint(self) -> str:
        return self.server.endpoint


@contextlib.asynccontextmanager
async def plant(tmp_path: Path, order: str = "big") -> AsyncIterator[Plant]:
    memory = MelsecMemory()
    memory.write_words("D", 100, [1234])
    memory.write_words("D", 150, [0xFFFE])  # -2
    memory.write_words("D", 120, [500])  # 50.0 %
    memory.write_words("D", 130, [0x1234])  # BCD 1234
    memory.write_words("D", 140, [7, 0xFFFF])
    memory.write_bits("M", 0, [True, False, True, True, False, False, False, True])
    memory.write_bits("M", 10, [True])
    memory.write_bits("M", 30, [True])
    sim = await e71.start(memory)
    path = tmp_path / "plant.toml"
    path.write_text(PLANT.format(order=order, url=sim.url, dead=free_port()))
    config = load_config(path)
    poller = Poller(config.poll)
    server = ModbusServer.from_config(poller, config.north.modbus)
    try:
        async with poller, server:
            await poller.write_tag("press1", "temp", 21.5)
            await poller.write_tag("press1", "total", -100000)
            await poller.write_tag("press1", "label", "ABC")
            async with fed(poller, server):
                async with asyncio.timeout(10):  # until both PLCs have been polled
                    while True:
                        if _polled(server):
                            break
                        await asyncio.sleep(0.02)
                yield Plant(memory, poller, server)
    finally:
        await sim.aclose()


def _polled(server: ModbusServer) -> bool:
    """Both PLCs polled, and the values written at the start seen by a poll since."""
    slots = server.image._by_tag
    expect = {"temp": 0x41AC, "total": 0xFFFE, "label": ord("A") << 8 | ord("B")}
    return (
        all(w in (slots[("press1", tag)].words or []) for tag, w in expect.items())
        and slots[("dead", "level")].why != "not polled yet"
    )


def _float(high: int, low: int) -> float:
    value: float = struct.unpack(">f", struct.pack(">HH", high, low))[0]
    return value


async def test_reads_of_every_function_code_answer_the_latest_poll(tmp_path: Path) -> None:
    async with plant(tmp_path) as p:
        fc3, fc4, fc1, fc2, text, scaled, bcd = await modbus(
            p.endpoint,
            *("rh", 0, 5),
            *("ri", 0, 1),
            *("rc", 0, 6),
            *("rd", 0, 8),
            *("rh", 10, 2),
            *("rh", 20, 2),
            *("rh", 30, 1),
        )
    words = [int(w) for w in fc3.split()[1:]]
    assert words[0] == 1234
    assert _float(words[1], words[2]) == 21.5  # high word first
    assert (words[3] << 16 | words[4]) - (1 << 32) == -100000
    assert fc4 == "ok 65534"  # int16 -2, two's complement
    assert fc1 == "ok 1 0 0 0 0 1"  # valve, pumps x4, door
    assert fc2 == "ok 1 0 1 1 0 0 0 1"
    assert text == f"ok {ord('A') << 8 | ord('B')} {ord('C') << 8}"
    high, low = (int(w) for w in scaled.split()[1:])
    assert _float(high, low) == 50.0  # engineering value of a scaled tag
    assert bcd == "ok 1234"  # the number, not its BCD pattern


async def test_word_order_little_sends_the_low_word_first(tmp_path: Path) -> None:
    async with plant(tmp_path, order="little") as p:
        (answer,) = await modbus(p.endpoint, "rh", 1, 4)
        (written,) = await modbus(
            p.endpoint, "whs", 1, 2, *struct.unpack(">HH", struct.pack(">f", -3.25))[::-1]
        )
        value = await p.poller.client("press1").read("D102", 2)
    low, high, total_low, total_high = (int(w) for w in answer.split()[1:])
    assert _float(high, low) == 21.5
    assert (total_high << 16 | total_low) - (1 << 32) == -100000
    assert written == "ok"
    assert _float(value[1], value[0]) == -3.25  # E71: low word first in D102, D103


async def test_exception_answers(tmp_path: Path) -> None:
    async with plant(tmp_path) as p:
        answers = await modbus(
            p.endpoint,
            *("rh", 50, 1),  # nothing mapped
            *("rh", 4, 3),  # total's low word, then hr:5 and hr:6 unmapped
            *("ri", 5, 1),  # the dead PLC's tag
            *("ri", 0, 6),  # mapped (ir:0, ir:5) and unmapped between: the gap decides
            *("rh", 2, 2),  # the low word of temp and the high word of total: fine
            *("rc", 5, 1),
        )
        wrong_unit = await modbus(p.endpoint, "rh", 0, 1, unit=7)
        any_unit = await modbus(p.endpoint, "rh", 0, 1, unit=255)
    assert answers[:4] == ["exc 0x02", "exc 0x02", "exc 0x0B", "exc 0x02"]
    assert answers[4].startswith("ok ")
    assert answers[5] == "ok 1"
    assert wrong_unit == ["exc 0x0A"]
    assert any_unit == ["ok 1234"]
    assert p.server.image.exceptions[0x02] == 3


async def test_writes_of_every_function_code_reach_the_plc(tmp_path: Path) -> None:
    async with plant(tmp_path) as p:
        high, low = struct.unpack(">HH", struct.pack(">f", 99.5))
        answers = await modbus(
            p.endpoint,
            *("wc", 0, 0),  # FC 5: valve off
            *("wcs", 1, 4, 1, 0, 1, 1),  # FC 15: pumps
            *("wh", 0, 4321),  # FC 6: strokes
            *("whs", 1, 2, high, low),  # FC 16: temp, a float32 in two registers
            *("whs", 40, 2, 5, 65535),  # FC 16: an array of two int16
            *("wh", 30, 42),  # bcd16 42 -> 0x0042 in the PLC
            *("whs", 10, 2, ord("h") << 8 | ord("i"), 0),  # a string
        )
        memory = p.memory
        assert answers == ["ok"] * 7
        # answered after the PLC confirmed: the memory holds the values already
        assert memory.read_bits("M", 10, 1) == [False]
        assert memory.read_bits("M", 20, 4) == [True, False, True, True]
        assert memory.read_words("D", 100, 1) == [4321]
        assert memory.read_words("D", 140, 2) == [5, 0xFFFF]
        assert memory.read_words("D", 130, 1) == [0x42]
        temp = await p.poller.client("press1").read("D102", 2)
        assert _float(temp[1], temp[0]) == 99.5  # E71: low word first
        assert p.server.image.writes_confirmed == 7


async def test_writes_refused_before_anything_is_sent(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    async with plant(tmp_path) as p:
        with caplog.at_level(logging.WARNING, logger="plcstack.north.modbus"):
            answers = await modbus(
                p.endpoint,
                *("wh", 3, 1),  # total is read-only
                *("wc", 5, 1),  # door is read-only
                *("wh", 1, 0),  # half of temp's float32
                *("wh", 40, 1),  # one element of the array pair
                *("wh", 30, 10000),  # bcd16 takes 0..9999
                *("wh", 50, 1),  # nothing there
            )
        before = p.memory.read_words("D", 100, 1)
    assert answers == ["exc 0x02", "exc 0x02", "exc 0x02", "exc 0x02", "exc 0x03", "exc 0x02"]
    assert before == [1234]
    assert p.memory.read_bits("M", 30, 1) == [True]
    assert "read-only" in caplog.text and "whole tags" in caplog.text
    # one WARNING per refusal: the write path's (with the audit), or here when no tag is there
    # (the runtime's "PLC ... is offline" of the dead PLC is not one of them)
    warnings = [
        r
        for r in caplog.records
        if r.levelno == logging.WARNING and r.name.startswith("plcstack.north.")
    ]
    assert len(warnings) == 6
    assert [r.name for r in warnings].count("plcstack.north.modbus") == 1


async def write_register(
    endpoint: str, transaction: int, address: int, value: int
) -> tuple[int, str]:
    """FC 6 over a connection of our own: the function code of the answer (0x86: an
    exception) and this end's ``host:port``, which the audit must name."""
    host, port = endpoint.rsplit(":", 1)
    reader, writer = await asyncio.open_connection(host, int(port))
    try:
        me = writer.get_extra_info("sockname")
        pdu = struct.pack(">BHH", 6, address, value)
        writer.write(struct.pack(">HHHB", transaction, 0, len(pdu) + 1, 1) + pdu)
        async with asyncio.timeout(10):
            head = await reader.readexactly(7)
            body = await reader.readexactly(struct.unpack(">H", head[4:6])[0] - 1)
    finally:
        writer.close()
        await writer.wait_closed()
    return body[0], f"{me[0]}:{me[1]}"


async def test_the_audit_names_the_modbus_client_of_each_write(tmp_path: Path) -> None:
    audit = Audit(AuditSettings(str(tmp_path / "writes.jsonl")))
    audit.open()
    try:
        async with plant(tmp_path) as p:
            p.server.writes = WritePath(p.poller, audit=audit)
            confirmed = await write_register(p.endpoint, 1, 0, 77)  # strokes
            refused = await write_register(p.endpoint, 2, 3, 1)  # half of total's int32
            failed = await write_register(p.endpoint, 3, 60, 1)  # the dead PLC's setpoint
    finally:
        audit.close()
    assert [answer for answer, _ in (confirmed, refused, failed)] == [0x06, 0x86, 0x86]
    assert p.memory.read_words("D", 100, 1) == [77]
    lines = [json.loads(x) for x in (tmp_path / "writes.jsonl").read_text().splitlines()]
    # refused before anything is sent, failed at the PLC, confirmed: each with its client
    assert [(x["source"], x["tag"], x["result"], x["peer"]) for x in lines] == [
        ("modbus", "strokes", "ok", confirmed[1]),
        ("modbus", "total", "bad_request", refused[1]),
        ("modbus", "setpoint", "plc_error", failed[1]),
    ]


async def test_a_write_to_a_dead_plc_is_refused_with_0x0b(tmp_path: Path) -> None:
    async with plant(tmp_path) as p:
        answers = await modbus(p.endpoint, "ri", 5, 1, "wh", 60, 1, "rh", 60, 1)
    assert answers == ["exc 0x0B"] * 3
    assert p.server.image.exceptions[0x0B] == 3


async def test_a_write_whose_outcome_is_unknown_is_an_exception_and_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    received = asyncio.Event()

    async def swallow(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError):
            while await reader.read(1024):
                received.set()  # takes the request, never answers
        writer.close()

    silent = await asyncio.start_server(swallow, "127.0.0.1", 0)
    port = silent.sockets[0].getsockname()[1]
    path = tmp_path / "silent.toml"
    path.write_text(
        '[modbus]\nlisten = "127.0.0.1:0"\n[[plc]]\nname = "mute"\n'
        f'url = "e71+tcp://127.0.0.1:{port}?timeout=0.3"\n[plc.tags]\n'
        'set = { address = "D0", type = "uint16", modbus = "hr:0", writable = true }\n'
    )
    config = load_config(path)
    poller = Poller(config.poll)
    server = ModbusServer.from_config(
        poller, config.north.modbus
    )  # not polling: only the write goes out
    try:
        async with server:
            with caplog.at_level(logging.WARNING, logger="plcstack.north.modbus"):
                answer = await modbus(server.endpoint, "wh", 0, 7)
    finally:
        await poller.aclose()
        silent.close()
        await silent.wait_closed()
    assert received.is_set()
    assert answer == ["exc 0x0B"]
    assert "outcome unknown" in caplog.text and "mute.set = 7" in caplog.text


def test_overlapping_tags_are_refused_naming_both_with_lines(tmp_path: Path) -> None:
    path = tmp_path / "overlap.toml"
    path.write_text(
        '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\n'
        'temp = { address = "D0", type = "float32", modbus = "hr:10" }\n'
        '[[plc]]\nname = "b"\nurl = "e71+tcp://127.0.0.1:2"\n[plc.tags]\n'
        'speed = { address = "D0", type = "uint16", modbus = "hr:11" }\n'
        'other = { address = "D1", type = "uint16", modbus = "ir:11" }\n'
    )
    with pytest.raises(ConfigError) as caught:
        load_config(path)  # every command that reads the file refuses it
    text = str(caught.value)
    assert "tag 'speed' of PLC 'b' (hr:11)" in text and f"{path}:10" in text
    assert "tag 'temp' of PLC 'a' (hr:10..11)" in text and f"{path}:5" in text
    poller = Poller(parse_poll_config(path.read_text(), source=str(path)))
    with pytest.raises(ConfigError) as again:
        ModbusServer.from_config(poller)  # and so does the Python API, in the same words
    assert str(again.value) == text


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ('modbus = "hx:1"', 'modbus must be "hr:N"'),
        ('modbus = "hr:70000"', "N 0..65535"),
        ('type = "float32", modbus = "co:0"', "a coil holds one bit"),
        ('type = "uint16", count = 3, modbus = "hr:65534"', "run past the last address"),
    ],
)
def test_bad_modbus_keys_are_config_errors_with_the_line(
    tmp_path: Path, spec: str, message: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(
        '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\n'
        f'x = {{ address = "D0", {spec} }}\n'
    )
    with pytest.raises(ConfigError, match=message) as caught:
        ModbusServer.from_config(Poller(load_config(path).poll))
    assert f"{path}:5" in str(caught.value)


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ('endpoint = "localhost"', 'endpoint must be "HOST:PORT"'),
        ("unit_id = 300", "unit_id must be 0..255"),
        ('word_order = "middle"', 'word_order must be "big" or "little"'),
        ("timeout = 1", r"unknown key\(s\) timeout"),
    ],
)
def test_bad_modbus_tables_are_config_errors(tmp_path: Path, table: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(
        f"[modbus]\n{table}\n"
        '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\n'
        'x = { address = "D0", modbus = "hr:0" }\n'
    )
    with pytest.raises(ConfigError, match=message) as caught:
        load_config(path)
    assert str(path) in str(caught.value)


def test_the_file_is_read_once_and_errors_still_name_its_lines(tmp_path: Path) -> None:
    """from_config takes what the loader parsed: with the file gone, an overlap is still
    reported at file:line (it used to read the file a second time for the lines)."""
    path = tmp_path / "once.toml"
    path.write_text(
        '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\n'
        'x = { address = "D0", modbus = "hr:0" }\n'
        'y = { address = "D1", modbus = "hr:0" }\n'
    )
    poller = Poller(parse_poll_config(path.read_text(), source=str(path)))
    path.unlink()
    with pytest.raises(ConfigError) as caught:
        ModbusServer.from_config(poller)
    assert f"{path}:5" in str(caught.value) and f"{path}:6" in str(caught.value)


def test_the_image_takes_scans(tmp_path: Path) -> None:
    from plcstack.north.modbus.frames import Request
    from plcstack.poll.samples import Quality, Sample, Scan

    path = tmp_path / "scans.toml"
    path.write_text(
        '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\n'
        'x = { address = "D0", type = "uint16", modbus = "hr:0" }\n'
        'y = { address = "D1", type = "uint16", modbus = "hr:1" }\n'
    )
    server = ModbusServer.from_config(Poller(load_config(path).poll))
    samples = (
        Sample("a", "x", 7, Quality.GOOD, 1.0, 1.1),
        Sample("a", "y", 9, Quality.GOOD, 1.0, 1.1),
    )
    server.submit([Scan("a", "default", 1.0, 1.1, samples)])
    # FC 3, read holding registers 0..1
    assert server.image.read(Request(1, 1, 3, 0, 2)) == [7, 9]


def test_a_config_without_modbus_keys_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "none.toml"
    path.write_text('[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\nx = "D0"\n')
    with pytest.raises(ConfigError, match="no tag has a modbus key"):
        ModbusServer.from_config(Poller(load_config(path).poll))
