"""One supervisor for every sink and server of the north side: nothing fails silently.

Two kinds of failure, one place that sees them:

* **A sink that cannot take a sample** (an encoder that raises for one value): the batch of
  scans is retried without it. With the sink's ``probe(sample)`` (raises for a sample it cannot
  take, no side effects) the culprits are found, replaced by a bad-quality copy naming the
  failure, and the batch goes again as a whole; without a probe, each sample goes alone (a scan
  of that one sample, with its PLC, group and times). So a failure costs at most
  that one sample. Each is counted (``plcstack_sink_errors_total{sink}``) and logged at ERROR with
  the PLC and tag, once per sink, PLC, tag and kind of error (later ones at DEBUG).
* **A sink or server task that dies** (an exception, or returning when it should run until
  cancelled): logged at ERROR with the reason, counted, and restarted after a growing, jittered
  backoff; meanwhile :meth:`Supervisor.health` names it, so ``/healthz`` answers 503.

The supervisor knows sinks only as names and callables, scans as records with ``samples`` and
samples as objects with ``plc`` and ``tag``: it does not depend on what a sink does.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, Protocol

from plcstack.errors import PlcError
from plcstack.poll.samples import Quality
from plcstack.resource import cancel_until_done
from plcstack.transports.backoff import Backoff

__all__ = ["Supervised", "Supervisor"]

log = logging.getLogger("plcstack.north.supervise")

#: a restarted task that then runs this long is healthy again: its backoff starts over
HEALTHY_AFTER = 60.0


def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def marked_bad(sample: Any, sink: str, exc: BaseException) -> Any:
    """A bad-quality copy of ``sample`` whose error says which sink could not take it and why."""
    error = f"{sink} could not take this value: {_describe(exc)}"
    try:
        return dataclasses.replace(
            sample, value=None, quality=Quality.BAD, error=error, error_type=None
        )
    except (TypeError, ValueError):  # a sample shape without these fields: it is only dropped
        return None


class Supervised:
    """One supervised task: the current task of a factory that the supervisor restarts."""

    def __init__(
        self, supervisor: Supervisor, name: str, factory: Callable[[], Coroutine[Any, Any, None]]
    ) -> None:
        self.supervisor = supervisor
        self.name = name
        self.factory = factory
        self.task: asyncio.Task[None] | None = None
        self.restarts = 0
        self.backoff = Backoff(initial=supervisor.initial, maximum=supervisor.maximum)
        self.stopping = False
        self._started = 0.0
        self._timer: asyncio.TimerHandle | None = None

    def _run(self) -> None:
        self._timer = None
        if self.stopping or self.supervisor.closing:
            return
        self.supervisor.down.pop(self.name, None)
        self._started = time.monotonic()
        self.task = asyncio.get_running_loop().create_task(self.factory(), name=self.name)
        self.task.add_done_callback(self._ended)

    def _ended(self, task: asyncio.Task[None]) -> None:
        if task.cancelled():
            return
        exc = task.exception()  # observed here, whatever happens next
        if self.stopping or self.supervisor.closing:
            if exc is not None:
                log.debug("%s ended while stopping: %s", self.name, _describe(exc))
            return
        reason = _describe(exc) if exc is not None else "it ended by itself"
        if time.monotonic() - self._started >= HEALTHY_AFTER:
            self.backoff.reset()
        delay = self.backoff.next_delay()
        self.restarts += 1
        self.supervisor.count(self.name)
        self.supervisor.down[self.name] = f"{self.name} failed ({reason}); restarting"
        log.error(
            "%s failed: %s; restarting in %.1f s",
            self.name,
            reason,
            delay,
            # a bug gets its traceback; a PlcError's message already says what happened
            exc_info=exc if exc is not None and not isinstance(exc, PlcError) else None,
            extra={"face": self.name},
        )
        self._timer = asyncio.get_running_loop().call_later(delay, self._run)

    async def stop(self) -> None:
        """Cancel the task until it has really ended; no restart after this."""
        self.stopping = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        task = self.task
        if task is None:
            return
        await cancel_until_done([task])  # one cancel may be dropped on Python 3.11
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task


class Supervisor:
    """Observes the sinks and servers of one run; see the module docstring."""

    def __init__(self, *, initial: float = 0.5, maximum: float = 30.0) -> None:
        self.initial = initial
        self.maximum = maximum
        #: sink or server name -> failures (samples it could not take, deaths of its task)
        self.errors: dict[str, int] = {}
        #: name -> why it is down, while a dead task waits for its restart
        self.down: dict[str, str] = {}
        self.closing = False
        self._tasks: list[Supervised] = []
        self._logged: set[tuple[str, str, str, str]] = set()

    def count(self, name: str, n: int = 1) -> None:
        self.errors[name] = self.errors.get(name, 0) + n

    # -- tasks ----------------------------------------------------------------------------------
    def start(self, name: str, factory: Callable[[], Coroutine[Any, Any, None]]) -> Supervised:
        """Run ``factory()`` as a task named ``name``, restarted with backoff when it fails."""
        handle = Supervised(self, name, factory)
        self._tasks.append(handle)
        handle._run()
        return handle

    def health(self) -> str | None:
        """None while every supervised task runs, else which are down and why."""
        if not self.down:
            return None
        return "; ".join(self.down[name] for name in sorted(self.down))

    async def aclose(self) -> None:
        self.closing = True
        for handle in self._tasks:
            await handle.stop()

    # -- scans ----------------------------------------------------------------------------------
    def submit(
        self,
        name: str,
        submit: Callable[[list[Any]], None],
        scans: Sequence[Any],
        probe: Callable[[Any], None] | None = None,
    ) -> None:
        """``submit(scans)``; if it raises, the scans again without the samples it cannot take.

        ``BrokenPipeError`` passes through: the reader of stdout went away, which ends a run
        deliberately.
        """
        batch = list(scans)
        try:
            submit(batch)
            return
        except BrokenPipeError:
            raise
        except Exception as exc:
            first: BaseException = exc
        if probe is not None:
            culprits = False
            fixed: list[Any] = []
            for scan in batch:
                kept: list[Any] = []
                for s in scan.samples:
                    try:
                        probe(s)
                    except Exception as exc:
                        culprits = True
                        self._lost(name, s, exc)
                        s = marked_bad(s, name, exc)
                    if s is not None:
                        kept.append(s)
                if kept:
                    fixed.append(scan.with_samples(tuple(kept)))
            if culprits:
                try:
                    submit(fixed)
                    return
                except BrokenPipeError:
                    raise
                except Exception as exc:
                    first = exc
                batch = fixed
            # no sample alone is at fault (or the fixed batch failed too): one at a time
        self._one_by_one(name, submit, batch, first)

    def _one_by_one(
        self, name: str, submit: Callable[[list[Any]], None], scans: list[Any], cause: BaseException
    ) -> None:
        """Each sample alone, as a scan of one sample (its PLC, group and times kept)."""
        log.debug("%s could not take a batch (%s); one sample at a time", name, _describe(cause))
        for scan in scans:
            for s in scan.samples:
                try:
                    submit([scan.with_samples((s,))])
                    continue
                except BrokenPipeError:
                    raise
                except Exception as exc:
                    self._lost(name, s, exc)
                    bad = marked_bad(s, name, exc)
                if bad is not None:
                    with contextlib.suppress(Exception):
                        submit([scan.with_samples((bad,))])

    def _lost(self, name: str, sample: Any, exc: BaseException) -> None:
        """Count a sample a sink could not take; log it at ERROR the first time per kind."""
        self.count(name)
        plc, tag = str(getattr(sample, "plc", "?")), str(getattr(sample, "tag", "?"))
        key = (name, plc, tag, type(exc).__name__)
        level = logging.DEBUG if key in self._logged else logging.ERROR
        self._logged.add(key)
        log.log(
            level,
            "%s: PLC %s tag %s: cannot take the value %r (%s); this sample is sent as bad"
            " quality or dropped, the sink goes on",
            name,
            plc,
            tag,
            getattr(sample, "value", None),
            _describe(exc),
            extra={"face": name, "plc": plc, "tag": tag},
        )


class Fed(Protocol):
    """A server fed from its poller's scans (the OPC UA and Modbus servers)."""

    async def run(
        self,
        observe: Callable[[list[Any]], object] | None = None,
        stored: Callable[[list[Any]], object] | None = None,
    ) -> None: ...


async def run_until(
    server: Fed,
    stop: asyncio.Event,
    timeout: float | None = None,
    observe: Callable[[list[Any]], object] | None = None,
    stored: Callable[[list[Any]], object] | None = None,
) -> None:
    """Feed a started server from its poller until ``stop`` is set or ``timeout`` seconds
    passed (``observe`` and ``stored``: see the server's ``run``).

    A failure of the feed itself (a bug) is raised, not swallowed with the cancellation, so a
    ``serve`` command ends with exit 1 and the reason instead of going on without its feed.
    """
    feeder = asyncio.create_task(server.run(observe, stored), name=f"{type(server).__name__} feed")
    stopper = asyncio.create_task(stop.wait(), name=f"{type(server).__name__} stop")
    try:
        await asyncio.wait({feeder, stopper}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in (feeder, stopper):
            task.cancel()
        await asyncio.gather(feeder, stopper, return_exceptions=True)
    if not feeder.cancelled() and (error := feeder.exception()) is not None:
        raise error
