"""The signals of every long-running plcstack command (``poll``, ``serve``, ``gateway``, ``sim``,
``demo``, a scale-out worker): SIGINT (Ctrl-C) and SIGTERM end it cleanly, so its statistics
still get printed (exit 130 after Ctrl-C, 0 after SIGTERM: how a supervisor such as systemd
ends a service, not a failure); SIGHUP never ends it.

SIGHUP is what ``systemctl reload`` and a closed terminal send; its default action ends a
Python process (exit 129, no statistics, the in-memory part of a queue lost, as ``kill -9``
would). A command that re-reads its configuration passes ``hangup``; for every other, a HUP is
logged once (WARNING, saying it is ignored) and later ones at DEBUG.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
from collections.abc import Callable
from typing import Any

__all__ = ["Signals", "StopEvent", "ended_early"]

log = logging.getLogger("plcstack.cli.signals")


class StopEvent(asyncio.Event):
    """Set to end the run; ``by`` is the signal that set it, if one did."""

    by: signal.Signals | None = None

    def exit_code(self) -> int:
        """130 after Ctrl-C (the rule for every subcommand), else 0: SIGTERM is how a
        supervisor (Telegraf's execd, systemd) ends a poller, not a failure."""
        return 130 if self.by is signal.SIGINT else 0


class Signals:
    """The signal handlers of one run: SIGINT/SIGTERM set ``stop`` (a graceful end, so the
    statistics still get printed); SIGHUP calls ``hangup`` (default: logged once and
    otherwise ignored, so a HUP never ends a plcstack process); ``on_stop`` is called after
    ``stop`` is set (a simulator cancels its serving task). ``with Signals(stop):`` installs
    them on the running loop and removes them after."""

    def __init__(
        self,
        stop: asyncio.Event,
        hangup: Callable[[], None] | None = None,
        *,
        on_stop: Callable[[], object] | None = None,
    ) -> None:
        self.stop = stop
        self.on_stop = on_stop
        self.hangup = hangup if hangup is not None else self._ignore_hangup
        self.hangups = 0
        self._installed: list[signal.Signals] = []

    def _stopped_by(self, sig: signal.Signals) -> None:
        stop = self.stop
        first = not stop.is_set()
        if isinstance(stop, StopEvent) and stop.by is None:
            stop.by = sig
        stop.set()
        if first and self.on_stop is not None:
            self.on_stop()

    def _hangup(self) -> None:
        self.hangups += 1
        self.hangup()

    def _ignore_hangup(self) -> None:
        level = logging.WARNING if self.hangups == 1 else logging.DEBUG
        log.log(
            level,
            "SIGHUP received: ignored (this command does not re-read anything on SIGHUP; it"
            " goes on as it was; SIGTERM or Ctrl-C end it)",
        )

    def __enter__(self) -> Signals:
        loop = asyncio.get_running_loop()
        handlers: list[tuple[signal.Signals, Callable[..., None], tuple[Any, ...]]] = [
            (signal.SIGINT, self._stopped_by, (signal.SIGINT,)),
            (signal.SIGTERM, self._stopped_by, (signal.SIGTERM,)),
            (signal.SIGHUP, self._hangup, ()),
        ]
        for sig, handler, args in handlers:
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(sig, handler, *args)
                self._installed.append(sig)
        return self

    def __exit__(self, *exc: object) -> None:
        loop = asyncio.get_running_loop()
        for sig in self._installed:
            loop.remove_signal_handler(sig)
        self._installed.clear()


def ended_early(done: set[asyncio.Task[Any]], stop: asyncio.Event) -> str | None:
    """Why a run ends before its time, from the tasks that should have run until cancelled:
    None if none of them ended (the duration ran out, or ``stop`` was set by a signal or a
    closed stdout), else one line naming the task and its exception."""
    for task in done:
        if task.cancelled():
            continue
        exc = task.exception()
        if exc is not None:
            log.debug("traceback of %s", task.get_name(), exc_info=exc)
            text = " ".join(str(exc).split())
            return f"{task.get_name()} failed: {type(exc).__name__}{': ' + text if text else ''}"
        if not stop.is_set():
            return f"{task.get_name()} ended unexpectedly"
    return None
