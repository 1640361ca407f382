"""Damaged state files: moved aside with one WARNING naming both paths, the run starts anew;
the audit, which is only ever appended to, starts each record on a line of its own."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import random
import sqlite3
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from plcstack.north.audit import Audit, AuditSettings
from plcstack.north.buffer import StoreAndForward
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.disk_helpers import fill, small_disk
from tests.north_helpers import subscriber
from tests.servers import Mosquitto

ROOT = Path(__file__).resolve().parent.parent


def queue_with_rows(path: Path, n: int = 400) -> None:
    q = StoreAndForward(path, memory_bytes=0)
    for i in range(n):
        q.put("plcstack/p/data/default", b"%05d" % i + b"." * 200)
    q.close()


def random_bytes(path: Path) -> None:
    path.write_bytes(random.Random(1).randbytes(8192))


def truncated(path: Path) -> None:
    queue_with_rows(path)
    os.truncate(path, path.stat().st_size // 2)


def page_garbage(path: Path) -> None:
    """4 KB of garbage over the second page (the first leaf of the queue table)."""
    queue_with_rows(path)
    with open(path, "r+b") as f:
        f.seek(4096)
        f.write(random.Random(2).randbytes(4096))


def foreign_schema(path: Path) -> None:
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE samples (ts REAL, value REAL)")
        db.execute("INSERT INTO samples VALUES (1.0, 2.0)")
    db.close()


def foreign_queue_table(path: Path) -> None:
    """Another program's table that happens to be called queue."""
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE queue (id INTEGER PRIMARY KEY, job TEXT)")
    db.close()


def foreign_application(path: Path) -> None:
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA application_id = 1234")
    db.close()


DAMAGE: dict[str, Callable[[Path], None]] = {
    "random bytes": random_bytes,
    "truncated": truncated,
    "page garbage": page_garbage,
    "foreign schema": foreign_schema,
    "foreign queue table": foreign_queue_table,
    "foreign application": foreign_application,
}


@pytest.mark.parametrize("kind", DAMAGE)
def test_a_damaged_queue_file_is_moved_aside_and_the_queue_starts_empty(
    kind: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "mqtt.sqlite"
    DAMAGE[kind](path)
    before = path.read_bytes()
    q = StoreAndForward(path)  # before: DatabaseError: file is not a database, run ended
    assert len(q) == 0 and q.failure is None
    q.put("t", b"new")
    q.close()
    [aside] = tmp_path.glob("mqtt.corrupt-*.sqlite")
    assert aside.read_bytes() == before  # kept as it was, for whoever wants to look
    [warning] = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert warning.levelno == logging.WARNING
    message = warning.getMessage()
    assert str(path) in message and str(aside) in message and "empty queue" in message
    assert [m.payload for m in StoreAndForward(path).peek(5)] == [b"new"]


def test_an_old_queue_file_without_the_mark_is_still_ours(tmp_path: Path) -> None:
    """Files written before they were marked (application_id 0) open with their messages."""
    path = tmp_path / "q.sqlite"
    with sqlite3.connect(path) as db:
        db.execute(
            "CREATE TABLE queue (seq INTEGER PRIMARY KEY, topic TEXT NOT NULL,"
            " payload BLOB NOT NULL, qos INTEGER NOT NULL, retain INTEGER NOT NULL)"
        )
        db.execute("INSERT INTO queue VALUES (7, 't', x'6f6c64', 1, 0)")
    db.close()
    q = StoreAndForward(path)
    assert [(m.seq, m.payload) for m in q.peek(5)] == [(7, b"old")]
    assert q.put("t", b"new").seq == 8
    q.close()
    assert not list(tmp_path.glob("*corrupt*"))


def test_a_queue_file_that_becomes_unreadable_is_moved_aside_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "q.sqlite"
    q = StoreAndForward(path, memory_bytes=0, max_bytes=1 << 30)
    for i in range(3000):  # 3 MB: more than SQLite keeps in its page cache
        q.put("t", b"%05d" % i + b"." * 1000)
    q.close()
    q = StoreAndForward(path, memory_bytes=0, max_bytes=1 << 30)
    assert q.peek(1)[0].payload[:5] == b"00000"  # the first rows are read ahead
    os.truncate(path, 100_000)  # the disk loses the rest under us
    head = q.peek(600)
    read_ahead = len(head)
    assert [int(m.payload[:5]) for m in head] == list(range(read_ahead))
    assert q.dropped == q.lost_to_disk == 3000 - read_ahead
    assert len(q) == read_ahead
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert (
        len(errors) == 1
        and f"the {3000 - read_ahead} messages waiting in it are lost" in (errors[0])
    )
    [aside] = tmp_path.glob("q.corrupt-*.sqlite")
    assert str(aside) in caplog.text
    q.put("t", b"after")
    assert q.peek(len(q))[-1].payload == b"after"
    q.close()


async def test_poll_runs_with_a_damaged_queue_file(mosquitto: Mosquitto, tmp_path: Path) -> None:
    """End to end: before, ``plcstack poll`` ended at once with ``internal error: DatabaseError:
    file is not a database`` (exit 1), the file not named, nothing published."""
    (tmp_path / "queue.sqlite").write_bytes(random.Random(3).randbytes(4096))
    sim = await e71.start(MelsecMemory())
    config = tmp_path / "plant.toml"
    config.write_text(
        f"""
[poll]
interval = 0.05
[[plc]]
name = "press1"
url = "{sim.url}"
[plc.tags]
n = {{ address = "D0", type = "uint16" }}
[mqtt]
url = "mqtt://{mosquitto.host}:{mosquitto.port}"
client_id = "damaged-queue"
buffer_path = "queue.sqlite"
"""
    )
    try:
        async with subscriber(mosquitto.host, mosquitto.port, "plcstack/+/data/#") as sub:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
                cwd=ROOT, stderr=asyncio.subprocess.PIPE,
            )  # fmt: skip
            try:
                # until it published, then stopped as a service is (SIGTERM): a fixed
                # --duration could end before a loaded machine had published anything
                await sub.wait_for(
                    lambda s: proc.returncode is not None or len(s.messages) > 0, timeout=30
                )
            finally:
                if proc.returncode is None:
                    proc.terminate()
                _, stderr = await asyncio.wait_for(proc.communicate(), 30)
            assert sub.messages, stderr.decode()
    finally:
        await sim.aclose()
    err = stderr.decode()
    assert proc.returncode == 0, err
    [aside] = await asyncio.to_thread(lambda: list(tmp_path.glob("queue.corrupt-*.sqlite")))
    assert f"{tmp_path / 'queue.sqlite'} is damaged (file is not a database)" in err
    assert f"moved aside to {aside}" in err


def audit_line(audit: Audit, value: object) -> bool:
    return audit.record(
        source="api", user=None, plc="p", tag="t", value=value, previous=None,
        result="ok", may_have_executed=True, peer=None, now=0.0,
    )  # fmt: skip


def records(path: Path) -> list[object]:
    """The values of the lines that are JSON records; a line that is not counts as None."""
    out: list[object] = []
    for line in path.read_text(errors="replace").splitlines():
        try:
            out.append(json.loads(line)["value"])
        except ValueError:
            out.append(None)
    return out


def test_an_audit_line_cut_short_by_a_crash_does_not_swallow_the_next(tmp_path: Path) -> None:
    path = tmp_path / "writes.jsonl"
    path.write_text('{"time": "2026-11-25T21:50:01.123Z", "source": "api", "us')
    audit = Audit(AuditSettings(str(path)))
    audit.open()
    assert audit_line(audit, 1) and audit_line(audit, 2)
    audit.close()
    assert records(path) == [None, 1, 2]  # before: [None, 2], the first record glued on


def test_an_audit_line_cut_short_by_a_full_disk_does_not_swallow_the_next(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk") as disk:
        path = disk / "writes.jsonl"
        audit = Audit(AuditSettings(str(path)))
        audit.open()
        assert audit_line(audit, 1)
        filler = fill(disk)
        assert not audit_line(audit, "x" * 20_000)  # the page it had is filled, then ENOSPC
        assert "No space left on device" in caplog.text
        filler.unlink()
        assert audit_line(audit, 3)
        audit.close()
        got = records(path)
        assert got[0] == 1 and got[-1] == 3 and set(got[1:-1]) <= {None}
