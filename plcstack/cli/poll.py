"""``plcstack poll CONFIG.toml``: poll every configured PLC, one sample per line on stdout.

stdout carries only samples (JSON lines or InfluxDB line protocol), so Telegraf's ``execd`` input
or a pipe can consume it; the statistics go to stderr when polling ends (``--duration`` elapsed,
Ctrl-C, SIGTERM, or the reader of stdout went away), with each sink's backlog and drops.

Exit 0 after ``--duration``, SIGTERM or a closed stdout; 130 after Ctrl-C; 1, with one line on
stderr saying what, when polling ended because something failed (it never ends early with 0);
2 for a bad configuration or a missing optional extra (the line names the pip install to run).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import logging
import os
import signal
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TextIO

from plcstack.cli import plain_text, print_error
from plcstack.cli.faces import gateway_faces
from plcstack.cli.pcap import add_pcap_options, with_pcap
from plcstack.cli.run_options import add_run_options, overrides_of, seconds
from plcstack.config import load_config
from plcstack.config.overrides import apply_overrides
from plcstack.errors import ConfigError
from plcstack.gateway.faces import GatewayFaces
from plcstack.north.influx import InfluxFormat
from plcstack.north.pipeline import North, missing, needs_of, sink_name
from plcstack.poll.config import PollConfig
from plcstack.poll.engine import Poller, format_stats
from plcstack.poll.samples import Scan
from plcstack.poll.sinks import FORMATS, each_line, jsonl_text
from plcstack.scale import cli as scale_cli
from plcstack.systemd.notify import Notifier
from plcstack.systemd.service import FleetStatus, ScanWatch, ServiceNotifier, stall_limit

if TYPE_CHECKING:
    from plcstack.scale.worker import Worker

log = logging.getLogger("plcstack.cli.poll")


def register(subparsers: Any) -> None:
    poll = subparsers.add_parser(
        "poll",
        help="poll the PLCs of a TOML config; samples on stdout, statistics on stderr",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    poll.add_argument(
        "config",
        help="TOML file with [[plc]] tables (an example: plcstack demo --write-config FILE)",
    )
    poll.add_argument(
        "--format",
        choices=[*sorted(FORMATS), "none"],
        default="jsonl",
        help="output format on stdout (default jsonl; none: only the sinks of the config, e.g."
        " [mqtt])",
    )
    add_run_options(poll)
    poll.add_argument(
        "--stats-every",
        type=seconds,
        default=None,
        metavar="SECONDS",
        help="also print the statistics on stderr every SECONDS (for long runs)",
    )
    scale_cli.add_arguments(poll)
    add_pcap_options(poll)
    poll.set_defaults(func=with_pcap(run_poll))


class StopEvent(asyncio.Event):
    """Set to end polling; ``by`` is the signal that set it, if one did."""

    by: signal.Signals | None = None

    def exit_code(self) -> int:
        """130 after Ctrl-C (the rule for every subcommand), else 0: SIGTERM is how a
        supervisor (Telegraf's execd, systemd) ends a poller, not a failure."""
        return 130 if self.by is signal.SIGINT else 0


def install_stop_signals(stop: asyncio.Event) -> list[signal.Signals]:
    """SIGINT/SIGTERM end polling gracefully (so the statistics still get printed)."""
    loop = asyncio.get_running_loop()
    installed = []

    def stopped_by(sig: signal.Signals) -> None:
        if isinstance(stop, StopEvent) and stop.by is None:
            stop.by = sig
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stopped_by, sig)
            installed.append(sig)
    return installed


def remove_stop_signals(installed: list[signal.Signals]) -> None:
    loop = asyncio.get_running_loop()
    for sig in installed:
        loop.remove_signal_handler(sig)


async def run_poll(args: argparse.Namespace, out: TextIO | None = None) -> int:
    out = out if out is not None else sys.stdout
    # read once; relative file paths in [mqtt] are taken relative to the TOML file
    whole = apply_overrides(load_config(args.config), overrides_of(args))
    config, north_config = whole.poll, whole.north
    needs = needs_of(north_config)
    if getattr(args, "mqtt", None) is not None:
        needs.append(("--mqtt (scale-out)", "aiomqtt", "scale"))
    if getattr(args, "nats", None) is not None:
        needs.append(("--nats (scale-out)", "nats", "scale"))
    problem = missing(needs)
    if problem is not None:
        print_error(f"poll: {problem}")
        return 2
    try:
        config = scale_cli.select(config, args)
        worker = scale_cli.make_worker(config, args)  # --mqtt: one worker of a cluster
    except ValueError as exc:
        print_error(f"poll: {exc}")
        return 2
    if whole.gateway and worker is not None:
        print_error(
            "poll: [[gateway]] faces stand on their PLC's one connection in this process; a"
            " scale-out worker (--mqtt, --nats) does not hold every PLC of the file"
        )
        return 2
    # every URL and address checked here, before anything is sent
    poller: Poller | Worker = worker if worker is not None else Poller(config)
    text: Callable[[list[Scan]], str] | None = None
    if args.format == "influx":
        text = InfluxFormat(
            config.plcs,
            layout=north_config.influx_layout,
            measurement=north_config.influx_measurement,
        ).text
    elif args.format == "jsonl":
        text = jsonl_text(config.plcs)
    elif args.format != "none":
        text = functools.partial(each_line, FORMATS[args.format])
    emit = _emitter(text, out)
    stop = StopEvent()
    installed = install_stop_signals(stop)
    north = North(poller, north_config)
    failure: str | None = None
    faces: GatewayFaces | None = None
    try:
        async with poller, north:
            if whole.gateway and isinstance(poller, Poller):
                faces = gateway_faces(whole.gateway, poller.client, north.writes)
                try:
                    await faces.aopen()
                except OSError as exc:
                    print_error(f"poll: a [[gateway]] face cannot listen: {exc.strerror or exc}")
                    return 2
                for line in faces.listening():
                    print(line, file=sys.stderr, flush=True)
            consumer = asyncio.create_task(
                _write_samples(north, emit, out, stop), name="the sample consumer"
            )
            stopper = asyncio.create_task(stop.wait())
            service = poll_service(poller, north, config)
            notifier = asyncio.create_task(
                service.run(), name="the notifications to the service manager"
            )
            reloads = asyncio.create_task(
                _reload_on_hangup(args.config, service), name="the reload on SIGHUP"
            )
            helpers = {consumer, stopper, notifier, reloads}
            if faces is not None:
                helpers.update(faces.workers)  # a PLC's face queue that ends ends the run
            every = getattr(args, "stats_every", None)
            if every is not None:
                helpers.add(
                    asyncio.create_task(_report_stats(poller, every), name="the statistics")
                )
            done, _ = await asyncio.wait(
                helpers, timeout=args.duration, return_when=asyncio.FIRST_COMPLETED
            )
            failure = ended_early(done - {stopper}, stop)
            service.stopping()
            if faces is not None:
                await faces.aclose()  # before the poller closes the PLCs' connections
            for task in helpers:
                task.cancel()
            await asyncio.gather(*helpers, return_exceptions=True)
            await poller.aclose()
            try:
                # samples of the last scans, taken after the consumer stopped: none is lost
                north.deliver(poller.drain(), emit)
            except BrokenPipeError:
                _silence_stdout(out)
    finally:
        remove_stop_signals(installed)
    print(format_stats(poller.stats, dropped_total=poller.dropped), file=sys.stderr)
    for summary in north.summary() + (faces.summary() if faces is not None else []):
        print(summary, file=sys.stderr)
    if failure is not None:
        print_error(f"poll: {failure}")
        return 1
    return stop.exit_code()


def poll_service(poller: Poller | Worker, north: North, config: PollConfig) -> ServiceNotifier:
    """What this run tells systemd (nothing without ``NOTIFY_SOCKET``): ready once the faces
    listen (they did when this is built) and every PLC had its first scan, the PLCs online and
    offline, watchdog pings while requests keep ending."""
    limit = stall_limit(config)
    fleet = FleetStatus(
        lambda: poller.stats,
        north.reachability.get,
        [sink_name(sink) for sink in north.sinks] + (["metrics"] if north.metrics else []),
    )
    return ServiceNotifier(
        Notifier.from_environment(),
        ready=fleet.ready,
        status=fleet.status,
        alive=ScanWatch(lambda: poller.stats, limit),
        ready_within=limit,
    )


async def _reload_on_hangup(path: str, service: ServiceNotifier) -> None:
    """SIGHUP (``systemctl reload``) reads the file again, between ``RELOADING=1`` and
    ``READY=1``: a file that does not load is said in one ERROR line and changes nothing."""
    hangups = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGHUP, hangups.set)
    try:
        while True:
            await hangups.wait()
            hangups.clear()
            service.reloading()
            try:
                load_config(path)
            except (ConfigError, OSError) as exc:
                problem = " ".join(str(exc).split())
                log.error("reload: %s does not load, nothing changed: %s", path, problem)
                service.reloaded(problem)
                continue
            log.warning(
                "reload: %s loads; this run keeps the configuration it started with:"
                " restart it to apply a change",
                path,
            )
            service.reloaded()
    finally:
        loop.remove_signal_handler(signal.SIGHUP)


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


async def _report_stats(poller: Poller | Worker, every: float) -> None:
    while True:
        await asyncio.sleep(every)
        print(format_stats(poller.stats, dropped_total=poller.dropped), file=sys.stderr, flush=True)


def _silence_stdout(out: TextIO) -> None:
    """The reader of stdout went away: point fd 1 at /dev/null so the interpreter's final flush
    does not print a traceback for a pipe nobody reads any more."""
    if out is sys.stdout:
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)


def _flush(out: TextIO) -> None:
    with contextlib.suppress(ValueError):
        out.flush()


def _emitter(
    text: Callable[[list[Scan]], str] | None, out: TextIO
) -> Callable[[list[Scan]], None] | None:
    if text is None:
        return None

    def emit(batch: list[Scan]) -> None:
        out.write(text(batch))
        _flush(out)  # a batch is written: hand it on before waiting for the next scan

    return emit


async def _write_samples(
    north: North, emit: Callable[[list[Scan]], None] | None, out: TextIO, stop: asyncio.Event
) -> None:
    try:
        await north.run(emit)
    except BrokenPipeError:
        _silence_stdout(out)
        stop.set()  # the reader went away: stop polling, still report statistics on stderr
