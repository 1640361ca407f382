"""One run of the runtime, as every command that polls runs it (``poll``, ``serve opcua``,
``serve modbus``): one poller, one connection per PLC, every face of the file on it.

The run starts the poller and every face (a face that cannot start: one line naming it, exit
2), prints where each face listens once every PLC's first scan is in (a client that connects
then reads values), consumes the scans until ``--duration``, SIGTERM, Ctrl-C or a closed stdout,
delivers the scans of the last requests, and prints the poller's statistics and one line per
face on stderr.

Signals (:mod:`plcstack.cli.signals`): SIGINT (Ctrl-C) and SIGTERM stop the run cleanly (exit
130 and 0); SIGHUP never ends it: it reads the file again and applies the difference
(:mod:`plcstack.cli.reload`, the path the web console's ``/api/config`` takes too), between
``RELOADING=1`` and ``READY=1`` under systemd; a file that does not load is one ERROR line and
changes nothing.

Under systemd (``NOTIFY_SOCKET``): ``READY=1`` once every PLC had its first scan, the PLCs
online and offline as ``STATUS``, watchdog pings while requests keep ending, ``STOPPING=1``
(:mod:`plcstack.systemd.service`).

Exit 0 after ``--duration``, SIGTERM or a closed stdout; 130 after Ctrl-C; 1, with one line on
stderr saying what, when the run ended because something failed (it never ends early with 0).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
from typing import Protocol, TextIO

from plcstack.cli import print_error
from plcstack.cli.reload import ReconfigurablePoller, Running, RuntimeControl
from plcstack.cli.signals import Signals, StopEvent, ended_early
from plcstack.gateway.faces import GatewayFaces
from plcstack.north.face import ScanSource
from plcstack.north.pipeline import North
from plcstack.poll.stats import format_stats
from plcstack.systemd.notify import Notifier
from plcstack.systemd.service import FleetStatus, ScanWatch, ServiceNotifier, StallLimit

log = logging.getLogger("plcstack.cli.runtime")

__all__ = ["RuntimePoller", "run_north", "silence_stdout"]


class RuntimePoller(ScanSource, ReconfigurablePoller, Protocol):
    """A poller as the runtime drives it and a reload changes it (a
    :class:`~plcstack.poll.engine.Poller`, or a scale-out :class:`~plcstack.scale.worker.
    Worker`)."""


def silence_stdout(out: TextIO) -> None:
    """The reader of stdout went away: point fd 1 at /dev/null so the interpreter's final flush
    does not print a traceback for a pipe nobody reads any more."""
    if out is sys.stdout:
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)


async def run_north(
    command: str,
    control: RuntimeControl,
    poller: RuntimePoller,
    north: North,
    *,
    duration: float | None,
    stats_every: float | None = None,
    out: TextIO | None = None,
    natives: GatewayFaces | None = None,
) -> int:
    """Run ``poller`` and every face of ``north`` (both of the configuration of ``control``,
    which a reload changes) until stopped; the exit code (see the module docstring).
    ``command`` prefixes the error line
    (``poll``, ``serve opcua``). ``natives``: the file's ``[[gateway]]`` faces on the PLCs'
    connections (a face that cannot listen: one line, exit 2; a PLC's face queue that ends ends
    the run)."""
    out = out if out is not None else sys.stdout
    stop = StopEvent()
    failure: str | None = None
    service = service_of(poller, north)
    hangups = asyncio.Event()
    with Signals(stop, hangups.set):
        await poller.start()
        try:
            await north.aopen()  # a face that cannot start: ConfigError naming it, exit 2
            try:
                if natives is not None:
                    try:
                        await natives.aopen()
                    except OSError as exc:
                        print_error(
                            f"{command}: a [[gateway]] face cannot listen: {exc.strerror or exc}"
                        )
                        return 2
                    for line in natives.listening():
                        print(line, file=sys.stderr, flush=True)
                control.attach(Running(poller, north, natives, service))
                failure = await _serve(
                    poller, north, out, stop, duration, stats_every, service, control, hangups,
                    natives,
                )  # fmt: skip
            finally:
                if natives is not None:
                    await natives.aclose()  # before the poller closes the PLCs' connections
                await north.aclose()
        finally:
            await poller.aclose()
    print(format_stats(dict(poller.stats), dropped_total=poller.dropped), file=sys.stderr)
    for line in north.summary() + (natives.summary() if natives is not None else []):
        print(line, file=sys.stderr)
    if failure is not None:
        print_error(f"{command}: {failure}")
        return 1
    return stop.exit_code()


def service_of(poller: ScanSource, north: North) -> ServiceNotifier:
    """What this run tells systemd (nothing without ``NOTIFY_SOCKET``): ready once the faces
    listen (they do when it runs) and every PLC had its first scan, the PLCs online and
    offline and the faces, watchdog pings while requests keep ending."""
    # the faces and the scans' limit as they are now: a reload may change both
    fleet = FleetStatus(
        lambda: poller.stats,
        north.reachability.get,
        lambda: [face.name for face in north.faces],
    )
    limit = StallLimit(lambda: poller.config)
    return ServiceNotifier(
        Notifier.from_environment(),
        ready=fleet.ready,
        status=fleet.status,
        alive=ScanWatch(lambda: poller.stats, limit),
        ready_within=limit(),
    )


async def _reloads(control: RuntimeControl, hangups: asyncio.Event) -> None:
    """Each SIGHUP (``systemctl reload``) reads the file again and applies the difference
    (:meth:`RuntimeControl.reload`): a file that does not load is said in one ERROR line and
    changes nothing."""
    while True:
        await hangups.wait()
        hangups.clear()
        await control.reload(who="SIGHUP")


async def _serve(
    poller: ScanSource,
    north: North,
    out: TextIO,
    stop: StopEvent,
    duration: float | None,
    stats_every: float | None,
    service: ServiceNotifier,
    control: RuntimeControl,
    hangups: asyncio.Event,
    natives: GatewayFaces | None,
) -> str | None:
    """Consume until the duration, a stop or a failure; the failure's line, if one ended it."""
    metrics = north.metrics
    if metrics is not None:
        print(f"metrics on {metrics.url}", file=sys.stderr, flush=True)
    consumer = asyncio.create_task(_consume(north, out, stop), name="the sample consumer")
    stopper = asyncio.create_task(stop.wait(), name="the stop")
    announcer = asyncio.create_task(_announce(north), name="the announcement")
    notifier = asyncio.create_task(service.run(), name="the notifications to the service manager")
    reloader = asyncio.create_task(_reloads(control, hangups), name="the reload on SIGHUP")
    helpers = {consumer, stopper, notifier, reloader}
    if stats_every is not None:
        helpers.add(asyncio.create_task(_report_stats(poller, stats_every), name="the statistics"))
    if natives is not None:
        # a PLC's face queue that stops by itself ends the run; one a reload closed does not
        helpers.add(asyncio.create_task(natives.watch(), name="the native faces"))
    try:
        done, _ = await asyncio.wait(helpers, timeout=duration, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in (*helpers, announcer):
            task.cancel()
        await asyncio.gather(*helpers, announcer, return_exceptions=True)
    failure = ended_early(done - {stopper}, stop)
    service.stopping()
    if natives is not None:
        await natives.aclose()  # before the poller closes the PLCs' connections
    await poller.aclose()
    try:
        # the scans of the last requests, taken after the consumer stopped: none is lost
        north.deliver(poller.drain())
    except BrokenPipeError:
        silence_stdout(out)
    return failure


async def _consume(north: North, out: TextIO, stop: asyncio.Event) -> None:
    try:
        await north.run()
    except BrokenPipeError:
        silence_stdout(out)
        stop.set()  # the reader went away: stop polling, still report statistics on stderr


async def _announce(north: North) -> None:
    """Where each face listens, once every PLC's first scan is in: the lines a script or an
    operator waits for, after which a client reads the PLCs' values."""
    await north.ready.wait()
    for line in north.announcements():
        print(line, file=sys.stderr, flush=True)


async def _report_stats(poller: ScanSource, every: float) -> None:
    while True:
        await asyncio.sleep(every)
        stats = format_stats(dict(poller.stats), dropped_total=poller.dropped)
        print(stats, file=sys.stderr, flush=True)
