"""A real ``plcstack poll`` with ``[history]`` killed with SIGKILL: the file it leaves is sound
and the next start has every point committed before the kill (the writer commits each second).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sqlite3
import sys
import time
from pathlib import Path

import pytest

from plcstack.north.history import History, HistorySettings
from plcstack.sim import e71 as e71_sim
from plcstack.sim.melsec_memory import MelsecMemory


def journal_rows(path: Path) -> int:
    if not path.exists():
        return 0
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return int(db.execute("SELECT COUNT(*) FROM journal").fetchone()[0])
    except sqlite3.OperationalError:
        return 0  # not created yet
    finally:
        db.close()


@pytest.mark.slow  # about 3 s: the poller's start and two commits a second apart
async def test_kill_9_leaves_a_sound_file_and_loses_at_most_the_last_second(
    tmp_path: Path,
) -> None:
    memory = MelsecMemory()
    sim = await e71_sim.start(memory)
    counter = 0

    async def count() -> None:
        nonlocal counter
        while True:
            counter += 1
            memory.write_words("D", 0, [counter])
            await asyncio.sleep(0.05)

    counting = asyncio.create_task(count())
    config = tmp_path / "plant.toml"
    config.write_text(
        '[poll]\ninterval = 0.1\n\n[history]\npath = "data/history.sqlite"\n\n'
        f'[[plc]]\nname = "press"\nurl = "{sim.url}"\n[plc.tags]\ncount = "D0"\n',
        encoding="utf-8",
    )
    path = tmp_path / "data" / "history.sqlite"
    proc = await asyncio.create_subprocess_exec(
        *[sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none"],
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 30
        while journal_rows(path) < 2:  # two commits: a second of points at least
            if proc.returncode is not None:
                assert proc.stderr is not None
                raise AssertionError(f"plcstack poll ended: {(await proc.stderr.read())!r}")
            assert time.monotonic() < deadline, "no journal rows after 30 s"
            await asyncio.sleep(0.1)
        os.kill(proc.pid, signal.SIGKILL)
        killed = time.time()
        await asyncio.wait_for(proc.wait(), 10)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        counting.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await counting
        await sim.aclose()
    assert proc.returncode == -signal.SIGKILL
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
    db.close()

    history = History(HistorySettings(path=path))
    await history.start()
    try:
        assert history.writer.stats.recovered >= 10  # 10 a second for a second at least
        points = await history.query("press", "count", killed - 60, killed, points=100_000)
    finally:
        await history.aclose()
    values = [v for _, v in points if isinstance(v, int)]
    assert len(values) == len(points) == history.writer.stats.recovered
    assert values == sorted(values) and len(set(values)) > 10  # the counter, as it moved
    assert killed - points[-1][0] < 2.5, "more than the last second was lost"
