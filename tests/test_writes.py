"""The one write path (north/writes.py) and its audit (north/audit.py), against a real simulator,
and the audit line of an MQTT write written before the answer goes back."""

from __future__ import annotations

import asyncio
import json
import logging
import sys
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from plcstack.north.audit import FIELDS, Audit, AuditSettings, parse_audit
from plcstack.north.writes import WritePath, WriteResult
from plcstack.poll.config import ConfigError, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.transports.peer import peer_address
from plcstack.values import INT16, UINT16
from tests.north_helpers import sample, subscriber
from tests.scan_helpers import scan
from tests.servers import Mosquitto

ROOT = Path(__file__).resolve().parent.parent


#: clients' addresses as the north sides hand them in
ANNA = "10.0.0.7:50412"
BOB = "[fd00::5]:41000"


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


async def test_each_attempt_is_answered_with_one_code_and_audited_in_order(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    memory = MelsecMemory()
    memory.write_words("D", 100, [7, 8])
    sim = await e71.start(memory)
    tags = (
        TagConfig("setpoint", "D100", INT16, writable=True),
        TagConfig("count", "D101", UINT16),
    )
    config = PollConfig((PlcConfig("press1", sim.url, tags),), {"default": 60})
    audit = Audit(AuditSettings(str(tmp_path / "writes.jsonl")))
    audit.open()
    try:
        async with Poller(config) as poller:
            path = WritePath(poller, audit=audit)
            path.observe([scan(sample("press1", "setpoint", 7))])
            with caplog.at_level(logging.INFO, "plcstack.north.writes"):
                results = [
                    await path.write("mqtt", None, "press1", "setpoint", 1201.0, peer=None),
                    await path.write("opcua", "anna", "press1", "count", 1, peer=ANNA),
                    await path.write("opcua", "anna", "press1", "count", 2, peer=ANNA),
                    await path.write("mqtt", None, "press1", "nope", 1, peer=None),
                    await path.write("mqtt", None, "press9", "setpoint", 1, peer=None),
                    await path.write("mqtt", None, "press1", "setpoint", "lots", peer=None),
                    path.refuse(
                        "web", "bob", "press1", "setpoint", 5, "busy", "queue full", peer=BOB
                    ),
                ]
    finally:
        audit.close()
        await sim.aclose()
    assert memory.read_words("D", 100, 1) == [1201]
    assert [(r.ok, r.code, r.may_have_executed) for r in results] == [
        (True, "ok", True),
        (False, "not_writable", False),
        (False, "not_writable", False),
        (False, "unknown_tag", False),
        (False, "unknown_plc", False),
        (False, "wrong_type", False),
        (False, "busy", False),
    ]
    assert isinstance(results[0], WriteResult)
    with pytest.raises(AttributeError):
        results[0].ok = False  # type: ignore[misc]  # frozen: an answer is not edited
    lines = _lines(tmp_path / "writes.jsonl")
    assert [tuple(line) for line in lines] == [FIELDS] * 7
    first = lines[0]
    assert first["time"].endswith("Z") and first["time"][10] == "T"
    assert {k: v for k, v in first.items() if k != "time"} == {
        "source": "mqtt",
        "user": None,
        "plc": "press1",
        "tag": "setpoint",
        "value": 1201.0,
        "previous": 7,
        "result": "ok",
        "may_have_executed": True,
        "peer": None,
    }
    assert [(x["source"], x["user"], x["result"], x["peer"]) for x in lines[1:]] == [
        ("opcua", "anna", "not_writable", ANNA),
        ("opcua", "anna", "not_writable", ANNA),
        ("mqtt", None, "unknown_tag", None),
        ("mqtt", None, "unknown_plc", None),
        ("mqtt", None, "wrong_type", None),
        ("web", "bob", "busy", BOB),
    ]
    # one WARNING per refusal that changed; the repeated one at DEBUG, the confirmed one at INFO
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 5
    assert warnings[0].startswith("write from opcua user anna refused (not_writable): press1:")
    assert warnings[0].endswith(f"; not attempted (client {ANNA})")
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert infos == ["write from mqtt: press1: write setpoint = 1201.0: confirmed by the PLC"]


def test_an_audit_that_cannot_be_written_is_an_error_and_counted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    failures: list[int] = []
    # a full disk: /dev/full opens, and every write to it fails with ENOSPC
    audit = Audit(AuditSettings("/dev/full"), on_error=lambda: failures.append(1))
    audit.open()
    with caplog.at_level(logging.ERROR, "plcstack.north.audit"):
        ok = audit.record(
            source="mqtt", user=None, plc="p", tag="t", value=1, previous=None,
            result="ok", may_have_executed=True, peer=None, now=0.0,
        )  # fmt: skip
    audit.close()
    assert not ok and failures == [1] and audit.failed == 1
    (error,) = [r.getMessage() for r in caplog.records]
    assert error.startswith("audit: cannot write /dev/full (No space left on device)")
    assert '"tag": "t"' in error  # the lost line is in the log at least


def test_a_full_file_is_rotated_and_backups_are_kept(tmp_path: Path) -> None:
    path = tmp_path / "writes.jsonl"
    audit = Audit(AuditSettings(str(path), max_bytes=4096, backups=2))
    audit.open()
    for i in range(200):
        audit.record(
            source="api", user=None, plc="p", tag="t", value=i, previous=None,
            result="ok", may_have_executed=True, peer=None, now=float(i),
        )  # fmt: skip
    audit.close()
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["writes.jsonl", "writes.jsonl.1", "writes.jsonl.2"]
    values = [
        line["value"]
        for name in ("writes.jsonl.2", "writes.jsonl.1", "writes.jsonl")
        for line in _lines(tmp_path / name)
    ]
    assert all(p.stat().st_size <= 4096 for p in tmp_path.iterdir())
    assert values == list(range(200 - len(values), 200))  # the newest, in order, none twice


def test_a_peer_is_spelled_host_colon_port() -> None:
    assert peer_address(("127.0.0.1", 50412)) == "127.0.0.1:50412"
    assert peer_address(("::1", 5020, 0, 0)) == "[::1]:5020"  # IPv6: bracketed, flow info dropped
    assert peer_address("/run/plc.sock") == "/run/plc.sock"
    assert peer_address(b"/run/plc.sock") == "/run/plc.sock"
    for nothing in (None, "", b"", (), ("host",)):
        assert peer_address(nothing) is None


def test_the_audit_table() -> None:
    assert parse_audit({"path": "w.jsonl"}, base=Path("/etc/plc")).path == "/etc/plc/w.jsonl"
    assert parse_audit({"path": "/var/w.jsonl"}, base=Path("/etc")).path == "/var/w.jsonl"
    for bad in ({}, {"path": ""}, {"path": "w", "max_bytes": 10}, {"path": "w", "size": 1}):
        with pytest.raises(ConfigError):
            parse_audit(bad)


async def test_poll_audits_an_mqtt_write_before_answering_it(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    memory = MelsecMemory()
    memory.write_words("D", 100, [7])
    sim = await e71.start(memory)
    (tmp_path / "etc").mkdir()
    config = tmp_path / "etc" / "plant.toml"
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
client_id = "audit-test"
[audit]
path = "writes.jsonl"
"""
    )
    audit = tmp_path / "etc" / "writes.jsonl"
    seen_at_answer: list[str] = []
    try:
        async with subscriber(mosquitto.host, mosquitto.port, "plcstack/#") as sub:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
                "--duration", "30", cwd=ROOT, stderr=asyncio.subprocess.PIPE,
            )  # fmt: skip
            try:
                await sub.wait_for(lambda s: any("/data/" in t for t, _ in s.messages), 15)
                async with aiomqtt.Client(mosquitto.host, mosquitto.port) as client:
                    await client.subscribe("plcstack/press1/write/resp", qos=1)
                    for request in ({"id": 1, "tag": "strokes", "value": 8}, {"id": 2}):
                        await client.publish(
                            "plcstack/press1/write/req", json.dumps(request), qos=1
                        )
                        async with asyncio.timeout(10):
                            async for _ in client.messages:
                                seen_at_answer.append(audit.read_text())
                                break
            finally:
                proc.terminate()
                _, err = await asyncio.wait_for(proc.communicate(), 20)
    finally:
        await sim.aclose()
    assert proc.returncode == 0, err.decode()
    # the line of each write was in the file when its answer arrived
    assert [len(text.splitlines()) for text in seen_at_answer] == [1, 2]
    lines = _lines(audit)
    assert [(x["source"], x["tag"], x["value"], x["previous"], x["result"]) for x in lines] == [
        ("mqtt", "strokes", 8, 7, "ok"),
        ("mqtt", "", None, None, "bad_request"),
    ]
    # the broker hides the publisher: the key is there, null
    assert [x["peer"] for x in lines] == [None, None]
    assert memory.read_words("D", 100, 1) == [8]
    # the refused write is said once at the default log level
    assert "write from mqtt refused (bad_request)" in err.decode()


async def test_a_misspelt_tag_is_answered_with_the_one_that_was_meant() -> None:
    sim = await e71.start(MelsecMemory())
    tags = (TagConfig("setpoint", "D100", INT16, writable=True),)
    config = PollConfig((PlcConfig("press1", sim.url, tags),), {"default": 60})
    try:
        async with Poller(config) as poller:
            path = WritePath(poller)
            result = await path.write("web", "anna", "press1", "setpont", 5, peer=ANNA)
            other = await path.write("web", "anna", "press1", "xyz", 5, peer=ANNA)
    finally:
        await sim.aclose()
    assert (result.code, result.may_have_executed) == ("unknown_tag", False)
    assert result.message == (
        "press1: write setpont: no tag named 'setpont' (did you mean setpoint?); not attempted"
    )
    assert other.message == "press1: write xyz: no tag named 'xyz'; not attempted"
