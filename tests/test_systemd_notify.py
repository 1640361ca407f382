"""The notify protocol to a stand-in of systemd's socket (tests/systemd_helpers.py), in-process:
the datagrams, the environment, failures said once, readiness, status, and the watchdog that
pings at the asked rate only while the loop and the work go on.

The whole command under systemd's variables (READY after the first scans, RELOADING/READY
around SIGHUP, STOPPING on SIGTERM) is in tests/test_systemd_poll.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from plcstack.poll.config import parse_poll_config as parse_config
from plcstack.poll.stats import PlcStats
from plcstack.systemd.notify import Notifier, monotonic_usec
from plcstack.systemd.service import (
    FleetStatus,
    ScanWatch,
    ServiceNotifier,
    StallLimit,
    stall_limit,
)
from tests.systemd_helpers import NotifySocket


@pytest.fixture
def sock(tmp_path: Path) -> Iterator[NotifySocket]:
    with NotifySocket(tmp_path) as s:
        yield s


@pytest.mark.parametrize("abstract", [False, True], ids=["path", "abstract"])
def test_one_datagram_per_message(tmp_path: Path, abstract: bool) -> None:
    with NotifySocket(tmp_path, abstract=abstract) as sock:
        notifier = Notifier(sock.address)
        assert notifier.enabled
        assert notifier.ready("3 PLCs: 3 online")
        assert notifier.status("two\nlines")  # a value never spans lines
        assert notifier.stopping()
        sock.wait_for("STOPPING")
        assert [m.fields for m in sock.received()] == [
            (("READY", "1"), ("STATUS", "3 PLCs: 3 online")),
            (("STATUS", "two lines"),),
            (("STOPPING", "1"),),
        ]
        notifier.close()


def test_reloading_says_when_it_began(sock: NotifySocket) -> None:
    notifier = Notifier(sock.address)
    before = monotonic_usec()
    notifier.reloading()
    after = monotonic_usec()
    message = sock.wait_for("RELOADING")
    assert message.names == ["RELOADING", "MONOTONIC_USEC"]
    assert before <= int(message.get("MONOTONIC_USEC") or 0) <= after
    # the same clock as CLOCK_MONOTONIC, which systemd compares it with
    assert abs(int(message.get("MONOTONIC_USEC") or 0) - time.monotonic() * 1e6) < 1e6


def test_the_environment(caplog: pytest.LogCaptureFixture) -> None:
    assert not Notifier.from_environment({}).enabled
    assert not Notifier.from_environment({}).send("READY=1")
    env = {"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "30000000"}
    assert Notifier.from_environment(env).watchdog_interval == 15.0
    mine = {**env, "WATCHDOG_PID": str(os.getpid())}
    assert Notifier.from_environment(mine).watchdog_interval == 15.0
    other = {**env, "WATCHDOG_PID": str(os.getpid() + 1)}  # a parent's watchdog, not ours
    assert Notifier.from_environment(other).watchdog_interval is None
    with caplog.at_level(logging.WARNING, "plcstack.systemd"):
        bad = Notifier.from_environment({**env, "WATCHDOG_USEC": "30s"})
        vsock = Notifier.from_environment({"NOTIFY_SOCKET": "vsock:2:1234"})
    assert bad.watchdog_interval is None
    assert not vsock.enabled
    assert [r.getMessage() for r in caplog.records] == [
        "WATCHDOG_USEC=30s is not a positive number: no watchdog pings",
        "NOTIFY_SOCKET=vsock:2:1234 is neither a socket path nor an abstract socket (@name):"
        " the service manager will not hear from plcstack",
    ]


def test_a_socket_that_fails_is_said_once_until_it_works(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "notify.sock"
    notifier = Notifier(str(path))
    with caplog.at_level(logging.WARNING, "plcstack.systemd"):
        assert not notifier.watchdog()
        assert not notifier.watchdog()
        with NotifySocket(tmp_path) as sock:
            assert notifier.watchdog()
            sock.wait_for("WATCHDOG")
    assert (notifier.sent, notifier.failed) == (1, 2)
    assert [r.getMessage() for r in caplog.records] == [
        f"cannot notify the service manager at {path} (WATCHDOG=1): No such file or directory:"
        " the notifications stop until the socket takes them again",
        f"the service manager at {path} takes notifications again",
    ]


async def _running(service: ServiceNotifier) -> asyncio.Task[None]:
    task = asyncio.create_task(service.run())
    await asyncio.sleep(0)
    return task


async def _stop(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


async def test_ready_once_ready_then_status_on_each_change(sock: NotifySocket) -> None:
    state = {"ready": False, "status": "1 PLC: 1 before its first scan (press1)"}
    service = ServiceNotifier(
        Notifier(sock.address),
        ready=lambda: bool(state["ready"]),
        status=lambda: str(state["status"]),
    )
    task = await _running(service)
    try:
        await asyncio.sleep(0.2)
        assert sock.received() == []  # not ready: nothing said
        state.update(ready=True, status="1 PLC: 1 online")
        ready = await sock.arrival("READY")
        assert ready.fields == (("READY", "1"), ("STATUS", "1 PLC: 1 online"))
        state["status"] = "1 PLC: 0 online, 1 offline (press1)"
        changed = await sock.arrival("STATUS", "1 PLC: 0 online, 1 offline (press1)")
        await asyncio.sleep(1.2)  # the status did not change again: not sent again
        assert sock.received()[-1] is changed
        assert len(sock.received()) == 2
    finally:
        await _stop(task)


async def test_ready_all_the_same_after_ready_within(
    sock: NotifySocket, caplog: pytest.LogCaptureFixture
) -> None:
    service = ServiceNotifier(
        Notifier(sock.address), ready=lambda: False, status=lambda: "x", ready_within=0.1
    )
    with caplog.at_level(logging.WARNING, "plcstack.systemd"):
        task = await _running(service)
        try:
            await sock.arrival("READY")
        finally:
            await _stop(task)
    assert "start-up not complete after 0 s (x): telling the service manager" in caplog.text


class _SendTimes(Notifier):
    """A notifier that notes when each ping was sent: the sender's times, not those at which
    a receiving thread of a loaded test machine got round to stamping them."""

    def __init__(self, address: str, watchdog_usec: int) -> None:
        super().__init__(address, watchdog_usec=watchdog_usec)
        self.ping_times: list[float] = []

    def watchdog(self) -> bool:
        self.ping_times.append(time.monotonic())
        return super().watchdog()


async def test_watchdog_pings_at_half_the_asked_interval(sock: NotifySocket) -> None:
    """WATCHDOG_USEC=600 ms: a ping every 300 ms (the first at once), never two further apart
    than the 600 ms systemd allows, and none before its time. Timed where the pings are sent
    (the receiving thread of a loaded machine may stamp them late)."""
    assert Notifier.from_environment(
        {"NOTIFY_SOCKET": sock.address, "WATCHDOG_USEC": "600000"}
    ).watchdog_interval == 0.3  # fmt: skip
    notifier = _SendTimes(sock.address, 600_000)
    reads: list[float] = []

    def clock() -> float:
        reads.append(time.monotonic())
        return reads[-1]

    service = ServiceNotifier(notifier, clock=clock)
    task = await _running(service)
    try:
        await asyncio.sleep(1.35)  # pings at 0, 0.3, 0.6, 0.9 and 1.2 s
    finally:
        await _stop(task)
    pings = notifier.ping_times
    gaps = [b - a for a, b in itertools.pairwise(pings)]
    assert len(await sock.count("WATCHDOG", len(pings))) == len(pings)  # each one went out
    assert 4 <= len(pings) <= 6, gaps
    assert max(gaps) < 0.6, gaps
    # not faster than asked either: the k-th ping never before its time, counted from the
    # start (one woken late is followed by the next on schedule: two may be closer than 300 ms)
    start = reads[0]
    for k, at in enumerate(pings):
        assert at >= start + k * 0.3, (k, gaps)


async def test_a_blocked_loop_sends_no_ping(sock: NotifySocket) -> None:
    """The pings come from the event loop: none is sent, and none arrives, while it is stuck
    for three watchdog intervals; they come again once it runs."""
    notifier = Notifier.from_environment({"NOTIFY_SOCKET": sock.address, "WATCHDOG_USEC": "200000"})
    service = ServiceNotifier(notifier)
    task = await _running(service)
    try:
        await sock.arrival("WATCHDOG")
        await asyncio.sleep(0.15)
        before = service.pings
        time.sleep(0.6)  # noqa: ASYNC251 - the event loop stuck for three watchdog intervals
        assert service.pings == before
        unblocked = time.monotonic()
        await sock.arrival("WATCHDOG", after=unblocked)
    finally:
        await _stop(task)
    # what had arrived by the end of the block was sent before it
    pings = [m.at for m in sock.with_field("WATCHDOG")]
    assert 1 <= len([at for at in pings if at < unblocked]) <= before
    assert service.pings > before


async def test_no_ping_while_the_work_stands_still(
    sock: NotifySocket, caplog: pytest.LogCaptureFixture
) -> None:
    stalled: dict[str, str | None] = {"why": None}
    notifier = Notifier.from_environment({"NOTIFY_SOCKET": sock.address, "WATCHDOG_USEC": "100000"})
    service = ServiceNotifier(notifier, alive=lambda: stalled["why"])
    with caplog.at_level(logging.WARNING, "plcstack.systemd"):
        task = await _running(service)
        try:
            await sock.arrival("WATCHDOG")
            stalled["why"] = "no request ended for 9 s"
            await asyncio.sleep(0.1)
            since = time.monotonic()
            await asyncio.sleep(0.4)
            assert [m for m in sock.with_field("WATCHDOG") if m.at > since] == []
            stalled["why"] = None
            await sock.arrival("WATCHDOG", after=time.monotonic())
        finally:
            await _stop(task)
    assert service.held >= 4
    assert [r.getMessage() for r in caplog.records] == [
        "watchdog: no ping to the service manager while no request ended for 9 s: systemd"
        " restarts the service when its WatchdogSec passes",
        "watchdog: work goes on again: pinging the service manager again",
    ]


async def test_reload_and_stop_hooks(sock: NotifySocket) -> None:
    service = ServiceNotifier(Notifier(sock.address), status=lambda: "2 PLCs: 2 online")
    task = await _running(service)
    try:
        await sock.arrival("READY")
        service.reloading()
        assert not service.is_ready
        service.reloaded()
        service.reloading()
        service.reloaded("plant.toml:3: [[plc]] needs url")
        service.stopping()
        service.stopping()  # once
        await sock.arrival("STOPPING")
    finally:
        await _stop(task)
    said = [m.names[0] + "=" + (m.get("STATUS") or "") for m in sock.received()]
    assert said == [
        "READY=2 PLCs: 2 online",
        "RELOADING=reloading the configuration",
        "READY=2 PLCs: 2 online",
        "RELOADING=reloading the configuration",
        "READY=reload failed, running as before: plant.toml:3: [[plc]] needs url",
        "STOPPING=stopping",
    ]


async def test_nothing_but_the_reload_says_ready_after_reloading(sock: NotifySocket) -> None:
    """A reload that takes a while (faces closed and started again): READY=1 comes when it is
    over, not from the status loop in the meantime. Before: the loop saw the service not
    ready, found every PLC scanned and said READY=1 within 50 ms of RELOADING=1."""
    service = ServiceNotifier(  # a 100 ms watchdog: the loop looks every 50 ms
        Notifier(sock.address, watchdog_usec=100_000),
        ready=lambda: True,
        status=lambda: "2 PLCs: 2 online",
    )
    task = await _running(service)
    try:
        await sock.arrival("READY")
        service.reloading()
        reloading = await sock.arrival("RELOADING")
        await asyncio.sleep(0.3)  # six looks of the loop while the reload goes on
        meanwhile = [m.names[0] for m in sock.received() if m.at > reloading.at]
        # a ping is said after the loop's look at readiness: the loop did look, said no READY
        assert meanwhile and set(meanwhile) == {"WATCHDOG"}, meanwhile
        service.reloaded()
        ready = await sock.arrival("READY", after=reloading.at)
        assert ready.fields == (("READY", "1"), ("STATUS", "2 PLCs: 2 online"))
        await asyncio.sleep(0.1)
        assert [m for m in sock.with_field("READY") if m.at > reloading.at] == [ready]
    finally:
        await _stop(task)


async def test_without_a_socket_nothing_happens() -> None:
    service = ServiceNotifier(Notifier(None), ready=lambda: True)
    assert not service.enabled
    task = await _running(service)
    await asyncio.sleep(0.05)
    assert not task.done() and not service.is_ready
    await _stop(task)


def test_scan_watch() -> None:
    now = [100.0]
    stats = {"a": PlcStats(), "b": PlcStats()}
    watch = ScanWatch(lambda: stats, 10.0, clock=lambda: now[0])
    assert watch() is None
    now[0] += 10
    assert watch() is None  # within the limit
    now[0] += 1
    assert watch() == (
        "no request of any of the 2 PLCs has ended (answered or failed) for 11 s (the scans'"
        " own limit: 10 s)"
    )
    stats["b"].requests += 1  # a failed request counts as one that ended
    assert watch() is None
    now[0] += 50
    assert ScanWatch(dict, 10.0, clock=lambda: now[0])() is None  # no PLC: nothing to stall


def test_stall_limit_takes_the_slowest_group_and_deadlines() -> None:
    config = parse_config(
        """
[groups]
slow = 10.0
[[plc]]
name = "a"
url = "e71+tcp://127.0.0.1:5000?timeout=4"
[plc.tags]
x = { address = "D0", group = "slow" }
[[plc]]
name = "b"
url = "s5lan://127.0.0.1:5010"
connect_timeout = 6.5
[plc.tags]
y = { address = "DB1.DW0" }
"""
    )
    # 2 x (10 s + the longest timeout + connect timeout of one PLC: b's 2 + 6.5)
    assert stall_limit(config) == 2 * (10.0 + max(4.0 + 3.0, 2.0 + 6.5))


def test_fleet_status() -> None:
    state: dict[str, bool | None] = {f"p{i}": None for i in range(8)}
    fleet = FleetStatus(lambda: {name: PlcStats() for name in state}, state.get, ["mqtt", "web"])
    assert not fleet.ready()
    assert fleet.status() == (
        "8 PLCs: 0 online, 8 before their first scan (p0, p1, p2, p3, p4 +3 more); faces: mqtt, web"
    )
    state.update({name: True for name in state})
    state["p3"] = False
    assert fleet.ready()
    assert fleet.status() == "8 PLCs: 7 online, 1 offline (p3); faces: mqtt, web"
    assert FleetStatus(lambda: {"a": PlcStats()}, lambda _: True).status() == "1 PLC: 1 online"


def test_the_scan_watch_follows_a_reload_of_the_scan_intervals() -> None:
    """A reload that slows the scans down (10 s where 0.1 s was): the watchdog judges by the
    new limit, so systemd does not kill a service whose scans go on. Before: the limit of
    the start (about 1 s here) held for ever, and the pings stopped."""
    text = """
[groups]
default = {interval}
[[plc]]
name = "a"
url = "e71+tcp://127.0.0.1:5000?timeout=0.2&connect_timeout=0.2"
[plc.tags]
x = {{ address = "D0" }}
"""
    configs = [parse_config(text.format(interval=0.1))]
    now = [100.0]
    stats = {"a": PlcStats()}
    watch = ScanWatch(lambda: stats, StallLimit(lambda: configs[0]), clock=lambda: now[0])
    assert watch.limit == 2 * (0.1 + 0.4)
    assert watch() is None
    configs[0] = parse_config(text.format(interval=10.0))  # the reloaded file
    now[0] += 5  # no request ended: a 10 s scan is not due yet
    assert watch.limit == 2 * (10.0 + 0.4)
    assert watch() is None
    now[0] += 20
    assert watch() is not None and "(the scans' own limit: 21 s)" in (watch() or "")


def test_fleet_status_names_the_faces_a_reload_left() -> None:
    faces = ["mqtt"]
    fleet = FleetStatus(lambda: {"a": PlcStats()}, lambda _: True, lambda: faces)
    assert fleet.status() == "1 PLC: 1 online; faces: mqtt"
    faces.append("web")  # [web] added by a reload
    assert fleet.status() == "1 PLC: 1 online; faces: mqtt, web"
