"""When a long-running command tells the service manager what: readiness, status, watchdog.

A command builds one :class:`ServiceNotifier` and runs its :meth:`~ServiceNotifier.run` as a
task beside its work; it calls :meth:`~ServiceNotifier.reloading` and
:meth:`~ServiceNotifier.reloaded` around a reload and :meth:`~ServiceNotifier.stopping` when it
begins to stop. What it needs to know of the command comes in as three small callables:

- ``ready()``: whether start-up is over. ``plcstack poll``: its faces listen (the task starts
  after they did) and every PLC had its first scan, answered or failed (:class:`FleetStatus`).
  After ``ready_within`` seconds ``READY=1`` is sent all the same, with a WARNING naming what
  is still missing: a PLC that never answers must not keep the whole service from starting.
- ``status()``: the one-line ``STATUS=`` that ``systemctl status`` shows, sent when it changes.
- ``alive()``: None while the work goes on, else why not. ``WATCHDOG=1`` is sent from the event
  loop, so a loop that is stuck sends none; and only while ``alive()`` is None, so a poller
  whose scans stopped (:class:`ScanWatch`) sends none either, and systemd restarts the service.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence

from plcstack.clients.base import DEFAULT_CONNECT_TIMEOUT, DEFAULT_TIMEOUT
from plcstack.poll.config import PollConfig
from plcstack.poll.stats import PlcStats
from plcstack.systemd.notify import Notifier
from plcstack.url import parse_url

__all__ = [
    "FleetStatus",
    "ScanWatch",
    "ServiceNotifier",
    "StallLimit",
    "notifying",
    "stall_limit",
]

log = logging.getLogger("plcstack.systemd")

#: seconds between two looks at the status and readiness once ready (the watchdog's own
#: interval when it is shorter)
STATUS_PERIOD = 1.0
#: seconds between two looks at readiness while starting
READY_PERIOD = 0.05
#: PLC names a status line lists before "+N more"
STATUS_NAMES = 5


def _always_alive() -> str | None:
    return None


class ServiceNotifier:
    """The notifications of one long-running command (nothing at all without a socket)."""

    def __init__(
        self,
        notifier: Notifier,
        *,
        ready: Callable[[], bool] | None = None,
        status: Callable[[], str] | None = None,
        alive: Callable[[], str | None] | None = None,
        ready_within: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.notifier = notifier
        self._ready = ready
        self._status = status
        self._alive = alive if alive is not None else _always_alive
        self.ready_within = ready_within
        self._clock = clock
        self._said: str | None = None
        self._stall: str | None = None
        #: ``READY=1`` was sent (and not yet followed by ``RELOADING=1``)
        self.is_ready = False
        #: between ``RELOADING=1`` and the reload's ``READY=1``: nothing else is said (a
        #: reload that restarts faces takes a while; ``READY=1`` before it is over would tell
        #: systemd the new configuration is in force while it is not yet)
        self._reloading = False
        self._stopping = False
        #: watchdog pings sent, and the ones held back because ``alive()`` said why not
        self.pings = 0
        self.held = 0

    @property
    def enabled(self) -> bool:
        return self.notifier.enabled

    def _text(self) -> str | None:
        return None if self._status is None else self._status()

    async def run(self) -> None:
        """Until cancelled: ``READY=1`` once ready, ``STATUS=`` on each change, ``WATCHDOG=1``
        at the asked interval while alive. Without a socket it only waits."""
        if not self.notifier.enabled:
            await asyncio.Event().wait()
        clock = self._clock
        start = clock()
        interval = self.notifier.watchdog_interval
        next_ping = start
        while True:
            now = clock()
            if self._stopping or self._reloading:
                pass  # the command says when that is over
            elif not self.is_ready:
                self._try_ready(now - start)
            else:
                self._say_status()
            if interval is not None and now >= next_ping:
                self._ping()
                next_ping = max(next_ping + interval, now)
            period = READY_PERIOD if not self.is_ready else STATUS_PERIOD
            if interval is not None:
                period = min(period, max(0.0, next_ping - clock()))
            await asyncio.sleep(period)

    def _try_ready(self, waited: float) -> None:
        ready = self._ready is None or self._ready()
        if not ready and waited < self.ready_within:
            return
        text = self._text()
        if not ready:
            log.warning(
                "start-up not complete after %.0f s (%s): telling the service manager the"
                " service is ready all the same",
                waited,
                text or "no status",
            )
        self.notifier.ready(text)
        self._said = text
        self.is_ready = True

    def _say_status(self) -> None:
        text = self._text()
        if text is not None and text != self._said:
            self.notifier.status(text)
            self._said = text

    def _ping(self) -> None:
        reason = self._alive()
        if reason is None:
            if self._stall is not None:
                log.warning("watchdog: work goes on again: pinging the service manager again")
                self._stall = None
            self.notifier.watchdog()
            self.pings += 1
            return
        self.held += 1
        if self._stall is None:
            log.error(
                "watchdog: no ping to the service manager while %s: systemd restarts the"
                " service when its WatchdogSec passes",
                reason,
            )
        self._stall = reason

    # -- the command's hooks ------------------------------------------------------------------
    def reloading(self) -> None:
        """A reload begins: ``RELOADING=1`` (with ``MONOTONIC_USEC``); call :meth:`reloaded`
        when it is over, whatever its outcome."""
        self.is_ready = False
        self._reloading = True
        self.notifier.reloading("reloading the configuration")

    def reloaded(self, problem: str | None = None, *, status: str | None = None) -> None:
        """The reload is over: ``READY=1``, with the status, or with ``problem`` (the file that
        did not load; the service runs on as before), or with ``status`` as it is given (a
        reload that failed part way)."""
        text = self._text()
        if problem is not None:
            text = f"reload failed, running as before: {problem}"
        if status is not None:
            text = status
        self.notifier.ready(text)
        self._said = text
        self.is_ready = True
        self._reloading = False

    def stopping(self, status: str | None = None) -> None:
        """The command begins to stop: ``STOPPING=1``, once."""
        if not self._stopping:
            self._stopping = True
            self.notifier.stopping(status or "stopping")


@contextlib.asynccontextmanager
async def notifying(service: ServiceNotifier) -> AsyncIterator[ServiceNotifier]:
    """``service.run()`` as a task for the body of the ``async with``; ``STOPPING=1`` when the
    body ends. A failure of the task is logged (ERROR) when it happens and raised at the end,
    so it is never lost; the command's work goes on meanwhile."""
    task = asyncio.create_task(service.run(), name="the notifications to the service manager")

    def failed(done: asyncio.Task[None]) -> None:
        if not done.cancelled() and done.exception() is not None:
            log.error("the notifications to the service manager stopped", exc_info=done.exception())

    task.add_done_callback(failed)
    try:
        yield service
    finally:
        service.stopping()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def stall_limit(config: PollConfig) -> float:
    """Seconds without any request of any PLC ending after which the scans count as stopped:
    twice the slowest scan interval plus the longest connect and request deadlines of a PLC
    (``[[plc]]`` keys, else the URL's options, else the clients' defaults). A PLC that is down
    fails its requests at once between reconnect attempts, so a poller whose scans go on ends
    a request well within this."""
    slowest = max(config.groups.values(), default=1.0)
    deadline = 0.0
    for plc in config.plcs:
        options = parse_url(plc.url).options
        timeout = plc.timeout or _seconds(options.get("timeout"), DEFAULT_TIMEOUT)
        connect = plc.connect_timeout or _seconds(
            options.get("connect_timeout"), DEFAULT_CONNECT_TIMEOUT
        )
        deadline = max(deadline, timeout + connect)
    return 2 * (slowest + deadline)


class StallLimit:
    """:func:`stall_limit` of the configuration a poller applies now (``config()``): a reload
    that slows the scans down (a minute where a second was) must not leave the watchdog
    waiting by the old limit, and systemd kill a service whose scans go on. Computed again
    only when the configuration is another one."""

    def __init__(self, config: Callable[[], PollConfig]) -> None:
        self._config = config
        self._of: PollConfig | None = None
        self._limit = 0.0

    def __call__(self) -> float:
        config = self._config()
        if config is not self._of:
            self._of, self._limit = config, stall_limit(config)
        return self._limit


def _seconds(text: str | None, default: float) -> float:
    try:
        return float(text) if text else default
    except ValueError:  # the client refuses it at start; a default here is good enough
        return default


class ScanWatch:
    """``alive()`` of a poller: None while some request of some PLC ended (answered or failed)
    within ``limit`` seconds, else the sentence that says how long none did.

    It reads the per-PLC request counters (``stats()``), which go up on every answer and every
    failure; a poller with no PLC (a scale-out worker that holds none) is alive."""

    def __init__(
        self,
        stats: Callable[[], Mapping[str, PlcStats]],
        limit: float | Callable[[], float],
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``limit``: seconds, or what says them now (:class:`StallLimit`: a reload may change
        the scan intervals)."""
        self._stats = stats
        self._limit = limit
        self._clock = clock
        self._total = -1
        self._since = clock()

    def __call__(self) -> str | None:
        stats = self._stats()
        total = sum(s.requests for s in stats.values())
        now = self._clock()
        if total != self._total or not stats:
            self._total, self._since = total, now
            return None
        idle = now - self._since
        limit = self.limit
        if idle <= limit:
            return None
        return (
            f"no request of any of the {len(stats)} PLCs has ended (answered or failed) for"
            f" {idle:.0f} s (the scans' own limit: {limit:.0f} s)"
        )

    @property
    def limit(self) -> float:
        """Seconds without a request ending after which the scans count as stopped, now."""
        limit = self._limit
        return limit if isinstance(limit, float | int) else limit()


class FleetStatus:
    """``ready()`` and ``status()`` of a poller: the PLCs it polls (``stats()``), whether each
    is reachable (``reachable(plc)``: None before its first scan) and its faces."""

    def __init__(
        self,
        stats: Callable[[], Mapping[str, PlcStats]],
        reachable: Callable[[str], bool | None],
        faces: Sequence[str] | Callable[[], Sequence[str]] = (),
    ) -> None:
        """``faces``: their names, or what says them now (a reload may add or remove one)."""
        self._stats = stats
        self._reachable = reachable
        self._faces = faces

    @property
    def faces(self) -> list[str]:
        faces = self._faces
        return list(faces() if callable(faces) else faces)

    def ready(self) -> bool:
        """Every PLC had its first scan (answered or failed)."""
        reachable = self._reachable
        return all(reachable(plc) is not None for plc in self._stats())

    def status(self) -> str:
        """``20 PLCs: 18 online, 2 offline (oven2, press3); faces: mqtt, web``."""
        online = 0
        offline: list[str] = []
        waiting: list[str] = []
        for plc in self._stats():
            state = self._reachable(plc)
            if state is None:
                waiting.append(plc)
            elif state:
                online += 1
            else:
                offline.append(plc)
        total = online + len(offline) + len(waiting)
        parts = [f"{online} online"]
        if offline:
            parts.append(f"{len(offline)} offline ({_names(offline)})")
        if waiting:
            parts.append(f"{len(waiting)} before their first scan ({_names(waiting)})")
        text = f"{total} PLC{'s' if total != 1 else ''}: {', '.join(parts)}"
        faces = self.faces
        if faces:
            text += f"; faces: {', '.join(faces)}"
        return text


def _names(plcs: list[str]) -> str:
    shown = sorted(plcs)[:STATUS_NAMES]
    more = len(plcs) - len(shown)
    return ", ".join(shown) + (f" +{more} more" if more else "")
