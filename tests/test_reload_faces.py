"""What a reload does to the embedded history and to systemd's view of it: a changed
``[history]`` closes the history and opens it again (the web console's trends then read the
reopened one), and a reload is framed by ``RELOADING=1`` and ``READY=1`` whatever happens in
between."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import aiohttp
import pytest

from plcstack.cli.reload import Running
from plcstack.north.history import History, HistoryBusy
from plcstack.north.web.server import WebConsole
from plcstack.poll.diff import PlcChanges
from plcstack.poll.engine import Applied, Poller
from plcstack.poll.samples import Quality, Scan, make_sample
from plcstack.sim.e71 import E71TcpSimulator
from plcstack.systemd.notify import Notifier
from plcstack.systemd.service import ServiceNotifier
from tests.aio_helpers import eventually
from tests.systemd_helpers import NotifySocket
from tests.test_reload import _file, _plc, running, sims


def _history(path: Path, retention: str) -> str:
    return f'[history]\npath = "{path}"\nretention = "{retention}"\n[web]\nlisten = "127.0.0.1:0"\n'


async def test_a_changed_history_table_reopens_the_history_the_console_reads(
    tmp_path: Path,
) -> None:
    path, store = tmp_path / "plant.toml", tmp_path / "h.sqlite"
    async with sims(1) as (sim,):
        assert isinstance(sim, E71TcpSimulator)
        memory = sim.memory
        memory.write_words("D", 100, [41])
        path.write_text(_file(_plc("press1", sim.url), head=_history(store, "7d")))
        async with running(path) as run:
            old = run.north.face(History)
            assert old is not None
            await eventually(lambda: run.scans("press1") >= 3, "press1 polled")
            since = time.time() - 60
            path.write_text(_file(_plc("press1", sim.url), head=_history(store, "2h")))
            outcome = await run.control.reload(who="test")
            assert outcome.ok, outcome
            new, web = run.north.face(History), run.north.face(WebConsole)
            assert new is not None and new is not old and web is not None
            assert new.settings.retention == 7200.0
            with pytest.raises(HistoryBusy, match="not open"):  # the old one let go of it
                await old.query("press1", "x", since, time.time())
            memory.write_words("D", 100, [42])
            await eventually(lambda: new.writer.stats.taken >= 2, "the reopened one records")
            await new.flush()
            query = f"{web.url}api/history?plc=press1&tag=x&from={since}"
            async with aiohttp.ClientSession() as http, http.get(query) as answer:
                assert answer.status == 200
                points = (await answer.json())["points"]
    values = [value for _, value in points]
    # what was recorded before the reload (41) and after it (42), from the one file
    assert values[0] == 41 and values[-1] == 42, values


class _PollerThatFails(Poller):
    """A poller whose apply fails in a way no reload expects (a defect, a cancellation)."""

    async def apply(self, changes: PlcChanges) -> Applied:
        raise RuntimeError("the poller could not take it")


async def test_a_reload_that_fails_part_way_still_ends_its_reloading(tmp_path: Path) -> None:
    """Before: RELOADING=1 was said and READY=1 never, so the service stayed "reloading" for
    systemd (and, since nothing else may say READY=1 during a reload, for good)."""
    path = tmp_path / "plant.toml"
    async with sims(1) as (sim,):
        path.write_text(_file(_plc("press1", sim.url)))
        async with running(path) as run:
            with NotifySocket(tmp_path) as sock:
                service = ServiceNotifier(Notifier(sock.address), status=lambda: "1 PLC")
                task = asyncio.create_task(service.run())
                try:
                    await sock.arrival("READY")
                    broken = _PollerThatFails(run.poller.config)
                    run.control.attach(Running(broken, run.north, None, service))
                    path.write_text(_file(_plc("press1", sim.url), _plc("oven2", sim.url)))
                    with pytest.raises(RuntimeError, match="could not take it"):
                        await run.control.reload(who="test")
                    reloading = await sock.arrival("RELOADING")
                    ready = await sock.arrival("READY", after=reloading.at)
                finally:
                    task.cancel()
                    await asyncio.gather(task, return_exceptions=True)
    assert (ready.get("STATUS") or "").startswith("reload failed part way: RuntimeError:")


async def test_the_scans_reported_while_a_face_restarts_reach_the_face_started_again(
    tmp_path: Path,
) -> None:
    """A face whose table changed is closed and started again; the scans reported meanwhile
    wait for the new one. Before, they went to the one closing (counted as dropped by the
    history, lost without a word by a closed MQTT queue)."""
    path, store = tmp_path / "plant.toml", tmp_path / "h.sqlite"
    async with sims(1) as (sim,):
        path.write_text(_file(_plc("press1", sim.url), head=_history(store, "7d")))
        async with running(path) as run:
            old = run.north.face(History)
            assert old is not None
            fed: list[int] = []

            async def feed() -> None:
                while True:
                    now = time.time()
                    value = len(fed)
                    sample = make_sample("press1", "fed", value, Quality.GOOD, now, now, None)
                    run.north.deliver([Scan("press1", "default", now, now, (sample,))])
                    fed.append(value)
                    await asyncio.sleep(0)

            feeder = asyncio.create_task(feed())
            try:
                await eventually(lambda: len(fed) >= 50, "scans fed before the reload")
                path.write_text(_file(_plc("press1", sim.url), head=_history(store, "2h")))
                outcome = await run.control.reload(who="test")
                assert outcome.ok, outcome
                during = len(fed)
                await eventually(lambda: len(fed) >= during + 50, "scans fed after the reload")
            finally:
                feeder.cancel()
                await asyncio.gather(feeder, return_exceptions=True)
            new = run.north.face(History)
            assert new is not None and new is not old
            assert old.late == 0, f"{old.late} samples went to the history being closed"
            await new.flush()
            points = await new.query("press1", "fed", 0, time.time() + 1, points=100_000)
    assert [value for _, value in points] == fed
