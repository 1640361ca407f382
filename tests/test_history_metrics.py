"""The embedded history's figures in ``/metrics``, read back with prometheus_client's own
parser: points taken and stored, write errors, bytes on disk, the oldest point's age, and the
queries answered with the time they took."""

from __future__ import annotations

from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.samples import Sample as PromSample

from plcstack.north.history import History, HistoryBusy, HistorySettings
from plcstack.north.history.writer import Writer
from plcstack.north.metrics import MetricsServer, PlcstackCollector, parse_metrics
from tests.test_history import T0, Clock, scan
from tests.test_north_metrics import http, idle_poller


async def scrape(server: MetricsServer) -> dict[str, list[PromSample]]:
    status, body = await http(server.port, b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
    assert status == 200, body
    return {f.name: f.samples for f in text_string_to_metric_families(body.decode())}


def value(families: dict[str, list[PromSample]], name: str, sample: str | None = None) -> float:
    (found,) = [s.value for s in families[name] if s.name == (sample or name)]
    return found


async def test_history_figures_in_metrics(tmp_path: Path) -> None:
    clock = Clock(T0 + 100)
    settings = HistorySettings(path=tmp_path / "h.sqlite")
    h = History(settings, clock=clock, writer=Writer(settings, clock=clock, checkpoint_every=0))
    collector = PlcstackCollector(idle_poller(), faces=lambda: [h])
    server = MetricsServer(collector, parse_metrics({"listen": "127.0.0.1:0"}))
    await h.start()
    await server.start()
    try:
        empty = await scrape(server)
        for i in range(40):
            h.submit(scan(T0 + i, temp=20.0 + i, on=i % 2 == 0))
        await h.flush()
        for _ in range(3):
            assert len(await h.query("p", "temp", T0, T0 + 100)) == 40
        clock.now = T0 + 250
        full = await scrape(server)
        on_disk = h.disk_bytes()
    finally:
        await server.aclose()
        await h.aclose()
    assert value(empty, "plcstack_history_points_taken", "plcstack_history_points_taken_total") == 0
    assert "plcstack_history_oldest_point_age_seconds" in empty  # the family, without a sample
    assert empty["plcstack_history_oldest_point_age_seconds"] == []

    def total(name: str) -> float:
        return value(full, f"plcstack_history_{name}", f"plcstack_history_{name}_total")

    assert total("points_taken") == 80
    assert total("points_stored") == 80  # checkpoint_every 0: every commit is a checkpoint
    assert total("write_errors") == total("dropped_points") == total("query_refusals") == 0
    assert value(full, "plcstack_history_oldest_point_age_seconds") == 250.0
    assert value(full, "plcstack_history_disk_bytes") == on_disk > 4096
    count = value(full, "plcstack_history_query_seconds", "plcstack_history_query_seconds_count")
    seconds = value(full, "plcstack_history_query_seconds", "plcstack_history_query_seconds_sum")
    assert count == 3 and 0 < seconds < 5


async def test_a_refused_query_is_counted(tmp_path: Path) -> None:
    h = History(HistorySettings(path=tmp_path / "h.sqlite"))
    server = MetricsServer(
        PlcstackCollector(idle_poller(), faces=lambda: [h]),
        parse_metrics({"listen": "127.0.0.1:0"}),
    )
    await server.start()
    try:
        with pytest.raises(HistoryBusy, match="not open"):  # not started yet
            await h.query("p", "temp", T0, T0 + 1)
        families = await scrape(server)
    finally:
        await server.aclose()
    refusals = "plcstack_history_query_refusals"
    assert value(families, refusals, refusals + "_total") == 1
    count = value(
        families, "plcstack_history_query_seconds", "plcstack_history_query_seconds_count"
    )
    assert count == 0
