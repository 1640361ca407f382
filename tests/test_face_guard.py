"""The guard every listening face shares (plcstack.transports.guard): its limits and their
configuration keys, the admission caps, the first-request and idle deadlines, and the burst log
that says a host's refusals, closes and garbage once per burst with a count."""

from __future__ import annotations

import asyncio
import logging

import pytest

from plcstack.checks import Table
from plcstack.errors import ConfigError
from plcstack.transports.guard import TOTALS, BurstLog, FaceGuard, Limits, parse_limits

log = logging.getLogger("tests.guard")


def test_limits_leave_a_quarter_to_other_hosts_and_say_themselves() -> None:
    assert Limits(max_clients=32).max_clients_per_host == 24
    assert Limits(max_clients=8).max_clients_per_host == 6
    assert Limits(max_clients=3).max_clients_per_host == 3
    assert Limits(max_clients=1).max_clients_per_host == 1
    assert Limits(max_clients=None).max_clients_per_host is None
    assert Limits(max_clients=16, idle_timeout=None).describe() == (
        "at most 16 clients, 12 per host; a first request within 10 s; idle clients kept"
    )
    with pytest.raises(ValueError, match=r"max_clients_per_host \(9\) cannot be more"):
        Limits(max_clients=8, max_clients_per_host=9)
    with pytest.raises(ValueError, match="first_request_timeout must be seconds"):
        Limits(first_request_timeout=0)


def test_parse_limits_keys_and_their_errors() -> None:
    defaults = Limits(max_clients=32, idle_timeout=600)

    def parse_limits_of(values: dict[str, object]) -> Limits:
        return parse_limits(Table(values, "modbus"), defaults)

    assert parse_limits_of({}) == defaults
    assert parse_limits_of({"first_request_timeout": "2s", "idle_timeout": "10m"}) == Limits(
        32, 24, 2.0, 600.0
    )
    got = parse_limits_of({"max_clients": 8, "first_request_timeout": 2, "idle_timeout": 0})
    assert got == Limits(8, 6, 2.0, None)
    refused: list[tuple[dict[str, object], str]] = [
        ({"max_clients": 0}, r"\[modbus\] max_clients must be 1..10000, not 0"),
        ({"max_clients_per_host": True}, "max_clients_per_host must be 1..10000"),
        ({"first_request_timeout": -1}, "first_request_timeout"),
        ({"idle_timeout": "ten"}, "idle_timeout"),
        ({"max_clients": 4, "max_clients_per_host": 5}, "cannot be more than max_clients"),
    ]
    for table, message in refused:
        with pytest.raises(ConfigError, match=message):
            parse_limits_of(table)


async def test_a_burst_is_said_once_then_counted(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, log.name)
    bursts = BurstLog(log, period=0.2)
    for _ in range(500):
        bursts.event(("10.0.0.7", "malformed"), "first one", "{n} more since {since}")
    assert [r.getMessage() for r in caplog.records] == ["first one"]
    await asyncio.sleep(0.3)  # one period: the rest in one line with the count
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and lines[1].startswith("499 more since ")
    await asyncio.sleep(0.5)  # a quiet period ends the burst; the next event starts one
    bursts.event(("10.0.0.7", "malformed"), "first again", "{n} more")
    assert [r.getMessage() for r in caplog.records][-1] == "first again"
    bursts.flush()


async def test_the_caps_refuse_by_host_and_in_all(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, log.name)
    guard = FaceGuard("test-face", "test face", Limits(max_clients=4, max_clients_per_host=1), log)
    before = TOTALS.get("test-face", "max_clients_per_host")
    visits = [guard.admit(("10.0.0.7", 1000 + i)) for i in range(3)]
    assert visits[0] is not None and visits[1] is None and visits[2] is None
    assert guard.counts["max_clients_per_host"] == 2
    assert TOTALS.get("test-face", "max_clients_per_host") == before + 2
    others = [guard.admit((f"10.0.0.{i}", 1)) for i in range(10, 14)]
    assert others[3] is None and guard.counts["max_clients"] == 1
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2, said  # once for 10.0.0.7, once for the cap in all
    assert "refusing 10.0.0.7:1001: one host may hold 1 connections" in said[0]
    for visit in [*visits, *others]:
        if visit is not None:
            visit.leave()
    assert guard.current == 0 and not guard.hosts
    guard.close()


async def test_a_visit_that_sends_no_request_ends_at_its_first_deadline() -> None:
    guard = FaceGuard("test-face", "test face", Limits(first_request_timeout=0.1), log)
    ended: list[str] = []
    silent = guard.admit(("10.0.0.7", 1), ended.append)
    talking = guard.admit(("10.0.0.8", 1), ended.append)
    assert silent is not None and talking is not None
    talking.served()
    await asyncio.sleep(0.25)
    assert ended == ["first_request_timeout"]
    assert guard.counts["first_request_timeout"] == 1
    silent.leave()
    talking.leave()
    guard.close()
