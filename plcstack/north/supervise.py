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

The supervisor knows sinks only as names and callables: it does not depend on what a sink
does. :meth:`Supervisor.health` says which tasks are down, why and since when, for ``/healthz``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Coroutine, Sequence

from plcstack.errors import PlcError
from plcstack.north.health import Health
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.resource import cancel_until_done
from plcstack.transports.backoff import Backoff

__all__ = ["Job", "Supervised", "Supervisor"]

#: what a supervised task runs: a coroutine function of no arguments, called again on a restart
Job = Callable[[], Coroutine[object, object, None]]

log = logging.getLogger("plcstack.north.supervise")

#: a restarted task that then runs this long is healthy again: its backoff starts over
HEALTHY_AFTER = 60.0


def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def marked_bad(sample: Sample, sink: str, exc: BaseException) -> Sample:
    """A bad-quality copy of ``sample`` whose error says which sink could not take it and why."""
    error = f"{sink} could not take this value: {_describe(exc)}"
    return dataclasses.replace(
        sample, value=None, quality=Quality.BAD, error=error, error_type=None
    )


class Supervised:
    """One supervised task: the current task of a factory that the supervisor restarts."""

    def __init__(
        self,
        supervisor: Supervisor,
        name: str,
        factory: Job,
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

    def launch(self) -> None:
        """Start the task now (the supervisor's first start, and each restart)."""
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
        self.supervisor.down.setdefault(self.name, (f"failed ({reason}); restarting", time.time()))
        log.error(
            "%s failed: %s; restarting in %.1f s",
            self.name,
            reason,
            delay,
            # a bug gets its traceback; a PlcError's message already says what happened
            exc_info=exc if exc is not None and not isinstance(exc, PlcError) else None,
            extra={"face": self.name},
        )
        self._timer = asyncio.get_running_loop().call_later(delay, self.launch)

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
        #: name -> (why it is down, since when), while a dead task waits for its restart
        self.down: dict[str, tuple[str, float]] = {}
        self.closing = False
        self._tasks: list[Supervised] = []
        self._logged: set[tuple[str, str, str, str]] = set()

    def count(self, name: str, n: int = 1) -> None:
        self.errors[name] = self.errors.get(name, 0) + n

    # -- tasks ----------------------------------------------------------------------------------
    def start(self, name: str, factory: Job) -> Supervised:
        """Run ``factory()`` as a task named ``name``, restarted with backoff when it fails."""
        handle = Supervised(self, name, factory)
        self._tasks.append(handle)
        handle.launch()
        return handle

    def health(self) -> list[Health]:
        """The supervised tasks that are down (why, since when), while they wait for their
        restart; empty while every one runs."""
        return [Health(name, reason, since) for name, (reason, since) in sorted(self.down.items())]

    async def aclose(self) -> None:
        self.closing = True
        for handle in self._tasks:
            await handle.stop()

    # -- scans ----------------------------------------------------------------------------------
    def submit(
        self,
        name: str,
        submit: Callable[[list[Scan]], None],
        scans: Sequence[Scan],
        probe: Callable[[Sample], None] | None = None,
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
            fixed: list[Scan] = []
            for scan in batch:
                kept: list[Sample] = []
                for s in scan.samples:
                    try:
                        probe(s)
                    except Exception as exc:
                        culprits = True
                        self._lost(name, s, exc)
                        s = marked_bad(s, name, exc)
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
        self,
        name: str,
        submit: Callable[[list[Scan]], None],
        scans: list[Scan],
        cause: BaseException,
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
                with contextlib.suppress(Exception):
                    submit([scan.with_samples((bad,))])

    def _lost(self, name: str, sample: Sample, exc: BaseException) -> None:
        """Count a sample a sink could not take; log it at ERROR the first time per kind."""
        self.count(name)
        plc, tag = sample.plc, sample.tag
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
            sample.value,
            _describe(exc),
            extra={"face": name, "plc": plc, "tag": tag},
        )
