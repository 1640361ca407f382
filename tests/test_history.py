"""The embedded history as a sink: what it keeps across restarts, checkpoints, retention, size,
a damaged file, a second writer, a full disk (a real 256 KiB tmpfs) and a writer that falls
behind. The kill -9 of a real ``plcstack poll`` is in tests/test_history_process.py.
"""

from __future__ import annotations

import asyncio
import logging
import sqlite3
from pathlib import Path
from typing import Any

import pytest

from plcstack.errors import ConfigError
from plcstack.north.config import parse_north
from plcstack.north.history import History, HistoryBusy, HistorySettings, parse_history
from plcstack.north.history.store import HistoryFile
from plcstack.north.history.writer import Writer
from plcstack.poll.samples import Quality, Scan, make_sample
from tests.disk_helpers import fill, small_disk

T0 = 1_800_000_000.0


def scan(t: float, **values: Any) -> list[Scan]:
    """One scan of PLC ``p`` at ``t`` with a sample per keyword (None: a bad sample)."""
    samples = tuple(
        make_sample("p", tag, v, Quality.GOOD, t, t + 0.01, None)
        if v is not None
        else make_sample("p", tag, None, Quality.BAD, t, t + 0.01, "p: timeout after 2.0 s")
        for tag, v in values.items()
    )
    return [Scan("p", "default", t, t + 0.01, samples)]


class Clock:
    def __init__(self, now: float = T0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def history(path: Path, clock: Clock, **writer: Any) -> History:
    settings = HistorySettings(path=path, retention=writer.pop("retention", 7 * 86400.0))
    return History(settings, clock=clock, writer=Writer(settings, clock=clock, **writer))


async def test_points_come_back_after_a_restart(tmp_path: Path) -> None:
    path, clock = tmp_path / "h.sqlite", Clock()
    h = history(path, clock)
    await h.start()
    for i in range(10):
        h.submit(scan(T0 + i, temp=20.5 + i, on=i % 2 == 0, count=i * 1000, text=f"s{i}"))
    h.submit(scan(T0 + 10, temp=None))
    await h.flush()
    assert await h.query("p", "count", T0, T0 + 100) == [(T0 + i, i * 1000) for i in range(10)]
    await h.aclose()

    h = history(path, clock)
    await h.start()
    try:
        temps = await h.query("p", "temp", T0 + 2, T0 + 100)
        assert temps == [(T0 + 2 + i, 22.5 + i) for i in range(8)] + [(T0 + 10, None)]
        assert await h.query("p", "on", T0 + 2.5, T0 + 4) == [
            (T0 + 2, True),  # the value that held at from
            (T0 + 3, False),
            (T0 + 4, True),
        ]
        assert (await h.query("p", "text", T0, T0 + 1))[-1] == (T0 + 1, "s1")
        assert await h.query("p", "nothing", T0, T0 + 100) == []
    finally:
        await h.aclose()


async def test_a_checkpoint_moves_the_journal_into_blocks(tmp_path: Path) -> None:
    path, clock = tmp_path / "h.sqlite", Clock()
    h = history(path, clock, checkpoint_every=3600.0, max_open_points=50)
    await h.start()
    try:
        for i in range(40):
            h.submit(scan(T0 + i, a=float(i), b=i))
            if i % 10 == 9:
                await h.flush()  # a commit a "second": four journal rows
        db = sqlite3.connect(path)
        # the third commit found 60 points open (more than 50): two blocks, the journal
        # emptied; the fourth commit's 20 points wait in one journal row
        assert db.execute("SELECT COUNT(*), SUM(n) FROM blocks").fetchone() == (2, 60)
        assert db.execute("SELECT COUNT(*) FROM journal").fetchone() == (1,)
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        db.close()
        # a query sees the stored and the open points, each once
        assert [v for _, v in await h.query("p", "b", T0, T0 + 40)] == list(range(40))
    finally:
        await h.aclose()


async def test_a_journal_is_replayed_after_a_crash(tmp_path: Path) -> None:
    """The process died after its last commit: the next start takes the journal back."""
    path, clock = tmp_path / "h.sqlite", Clock()
    h = history(path, clock)
    await h.start()
    for i in range(5):
        h.submit(scan(T0 + i, a=i))
    await h.flush()
    # what kill -9 leaves: the file as committed, the lock released with the process
    h.writer.file.db.close()  # type: ignore[union-attr]
    h.writer.file = None
    h.writer.close()
    h._shutdown_pools()

    again = history(path, clock)
    await again.start()
    try:
        assert again.writer.stats.recovered == 5
        assert [v for _, v in await again.query("p", "a", T0, T0 + 10)] == [0, 1, 2, 3, 4]
    finally:
        await again.aclose()


async def test_retention_deletes_what_is_older(tmp_path: Path) -> None:
    path, clock = tmp_path / "h.sqlite", Clock()
    h = history(path, clock, retention=3600.0, checkpoint_every=0.0)
    await h.start()
    try:
        h.submit(scan(T0, a=1))
        await h.flush()  # a block ending at T0
        clock.now = T0 + 7200
        h.submit(scan(T0 + 7200, a=2))
        await h.flush()  # the next checkpoint deletes the first block
        assert h.writer.stats.expired == 1
        assert await h.query("p", "a", T0 - 10, T0 + 7300) == [(T0 + 7200, 2)]
    finally:
        await h.aclose()


def test_max_size_deletes_the_oldest_blocks(tmp_path: Path) -> None:
    file = HistoryFile(tmp_path / "h.sqlite")
    try:
        rows = [(1, t, t + 100, 100, bytes(1000)) for t in range(0, 100_000, 100)]
        file.begin()
        file.checkpoint(rows)
        file.commit()
        before = file.used_bytes()
        assert before > 1_000_000
        file.begin()
        deleted = file.trim(300_000)
        file.commit()
        assert file.used_bytes() <= 300_000
        oldest = file.db.execute("SELECT MIN(t0), COUNT(*) FROM blocks").fetchone()
        assert oldest == (deleted * 100, 1000 - deleted)  # the oldest went first
    finally:
        file.close()


async def test_a_damaged_file_is_moved_aside_with_one_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "h.sqlite"
    path.write_bytes(b"SQLite format 3\x00" + bytes(range(256)) * 20)
    h = history(path, Clock())
    with caplog.at_level(logging.WARNING, logger="plcstack.history"):
        await h.start()
    try:
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1, warnings
        assert warnings[0].startswith(f"history {path} is damaged (")
        assert "moved aside to" in warnings[0] and "a new history starts" in warnings[0]
        assert len(moved_aside(tmp_path)) == 1
        h.submit(scan(T0, a=1))
        await h.flush()
        assert await h.query("p", "a", T0, T0 + 1) == [(T0, 1)]
    finally:
        await h.aclose()


async def test_a_file_of_something_else_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "plant.sqlite"
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE recipes (name TEXT)")
    db.commit()
    db.close()
    with pytest.raises(ConfigError, match="SQLite file of something else.*recipes"):
        await history(path, Clock()).start()
    assert sqlite3.connect(path).execute("SELECT COUNT(*) FROM recipes").fetchone() == (0,)


@pytest.mark.parametrize(
    ("path", "reason"),
    [
        ("/proc/nowhere/h.sqlite", "No such file or directory (/proc/nowhere)"),
        ("/sys/h.sqlite", "Permission denied (/sys/h.sqlite.lock)"),
    ],
)
async def test_a_place_that_cannot_hold_a_file_is_said_at_start(path: str, reason: str) -> None:
    with pytest.raises(ConfigError) as caught:
        await history(Path(path), Clock()).start()
    assert str(caught.value) == f"[history] cannot keep the history in {path}: {reason}"


async def test_a_second_writer_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "h.sqlite"
    first = history(path, Clock())
    await first.start()
    try:
        with pytest.raises(ConfigError, match=r"in use by process \d+"):
            await history(path, Clock()).start()
    finally:
        await first.aclose()


async def test_a_writer_that_falls_behind_drops_and_says_so_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    h = History(HistorySettings(path=tmp_path / "h.sqlite"), queue_limit=10)
    await h.start()
    try:
        with caplog.at_level(logging.WARNING, logger="plcstack.history"):
            for i in range(5):
                h.submit(scan(T0 + i, a=1, b=2, c=3, d=4))  # 4 samples each: 2 fit
            await h.flush()
        assert h.dropped == 12
        lines = [r.getMessage() for r in caplog.records]
        assert len(lines) == 2, lines
        assert "8 samples wait for the writer" in lines[0] and "dropped" in lines[0]
        assert lines[1] == "history: writing again after dropping 12 samples"
        assert "12 dropped" in h.summary()
    finally:
        await h.aclose()


def moved_aside(directory: Path) -> list[str]:
    return [p.name for p in directory.iterdir() if p.name.startswith("h.corrupt-")]


async def test_a_full_disk_keeps_the_points_in_memory_until_it_has_room(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "small") as disk:
        clock = Clock()
        h = history(disk / "h.sqlite", clock, checkpoint_every=0.0)
        await h.start()
        try:
            with caplog.at_level(logging.WARNING, logger="plcstack.history"):
                filler = fill(disk)
                for i in range(300):
                    h.submit(scan(T0 + i, **{f"t{k}": float(i * k) for k in range(20)}))
                    if i % 30 == 29:
                        await h.flush()
                failures = h.writer.stats.failures
                assert failures > 0
                down = h.health()
                filler.unlink()
                await h.flush()
            assert down.problem is not None and down.since == T0, down
            assert down.problem.startswith(f"cannot write to {disk / 'h.sqlite'} (Operational")
            assert "full" in down.problem and dict(down.figures)["points waiting in memory"] > 0
            assert h.health().ok  # writing again: healthy, said in /healthz as "history: ok"
            lines = [r.getMessage() for r in caplog.records]
            assert len(lines) == 2, lines
            assert "cannot write to" in lines[0] and "full" in lines[0]
            assert "points wait in memory" in lines[0]
            assert lines[1].startswith("history: writing to ") and "again" in lines[1]
            got = await h.query("p", "t7", T0, T0 + 300, points=1000)
            assert [v for _, v in got] == [float(i * 7) for i in range(300)]
        finally:
            await h.aclose()


def test_history_table() -> None:
    base = Path("/etc/plant")
    settings = parse_history({"retention": "12h", "max_size": "20MB"}, base=base)
    assert settings == HistorySettings(base / "history.sqlite", 43200.0, 20_000_000)
    assert parse_history({"path": "/var/h.sqlite", "retention": 7200}, base=base).path == Path(
        "/var/h.sqlite"
    )
    assert parse_north({"history": {"path": "x.sqlite"}}, base=base).history == HistorySettings(
        base / "x.sqlite"
    )


@pytest.mark.parametrize(
    ("table", "problem"),
    [
        ({"retension": "7d"}, "unknown key(s) retension (did you mean retention?)"),
        ({"retention": "7 days"}, 'or a duration such as "500ms", "30s", "15m", "12h", "7d"'),
        ({"retention": "5m"}, "retention must be at least 10 minutes, not '5m'"),
        ({"retention": -1}, "retention must be a number of seconds (greater than 0)"),
        ({"max_size": "lots"}, 'max_size must be a number of bytes (4194304, "4 MiB"'),
        ({"max_size": "1MB"}, "max_size must be 4 MiB to 1024 TiB, not '1MB'"),
        ({"path": ""}, "path must name a file"),
        ({"path": 5}, "path must name a file"),
    ],
)
def test_history_table_errors(table: dict[str, Any], problem: str) -> None:
    with pytest.raises(ConfigError) as caught:
        parse_history(table)
    assert problem in str(caught.value)


async def test_a_query_waits_for_no_commit(tmp_path: Path) -> None:
    """Queries run in their own thread: one during a commit is answered, not refused."""
    h = history(tmp_path / "h.sqlite", Clock())
    await h.start()
    try:
        for i in range(2000):
            h.submit(scan(T0 + i, a=float(i)))
        flush = asyncio.ensure_future(h.flush())
        got = await h.query("p", "a", T0, T0 + 3000, points=4)
        await flush
        assert len(got) <= 4
    finally:
        await h.aclose()


async def test_a_reload_closes_the_history_and_opens_it_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """What a reload of a changed [history] does to the face: the old one closes (its points
    written, the write-ahead log emptied, the file released), the new one opens the same file
    with the new table (a shorter retention deletes at once) or a new file."""
    path, clock = tmp_path / "h.sqlite", Clock()
    old = history(path, clock, checkpoint_every=0.0)
    await old.start()
    for i in range(10):
        old.submit(scan(T0 + i, count=i))
    await old.flush()  # a checkpoint: one block of the first ten seconds
    for i in range(650, 660):
        old.submit(scan(T0 + i, count=i))  # queued, not yet written: the close writes them
    await old.aclose()
    with caplog.at_level(logging.WARNING, logger="plcstack.history"):
        # scans the runtime hands over while the reload has closed this one and not yet
        # opened the next: counted, said once (before: kept in a queue no one wrote)
        old.submit(scan(T0 + 660, count=660, other=1))
        old.submit(scan(T0 + 661, count=661))
    assert (old.late, old.dropped) == (3, 3)
    (said,) = [r.getMessage() for r in caplog.records]
    assert said.startswith(f"history: samples arrive while {path} closes (a reload restarts")
    wal = path.with_name(path.name + "-wal")
    assert not wal.exists() or wal.stat().st_size == 0  # checkpointed into the file
    with pytest.raises(HistoryBusy, match="not open"):
        await old.query("p", "count", T0, T0 + 700)

    clock.now = T0 + 700
    new = history(path, clock, retention=600.0)  # the reloaded table: the same file
    await new.start()  # the old one let go of it: no "in use by process"
    try:
        assert new.writer.stats.expired == 1  # the first block is older than the new retention
        got = await new.query("p", "count", T0, T0 + 700)
        assert got == [(T0 + i, i) for i in range(650, 660)]
        new.submit(scan(T0 + 700, count=700))
        await new.flush()
        assert (await new.query("p", "count", T0 + 690, T0 + 710))[-1] == (T0 + 700, 700)
    finally:
        await new.aclose()

    moved = history(tmp_path / "elsewhere.sqlite", clock)  # a reload to a new path
    await moved.start()
    try:
        assert await moved.query("p", "count", T0, T0 + 800) == []
        again = history(path, clock)  # the old file is free for anyone
        await again.start()
        await again.aclose()
    finally:
        await moved.aclose()
