"""``plcstack poll CONFIG.toml``: poll every configured PLC and serve every face of the file.

One process, one poller, one connection per PLC: the samples on stdout (JSON lines or InfluxDB
line protocol, so Telegraf's ``execd`` input or a pipe can consume them) and every face the
file configures on the same scans: ``[mqtt]`` (JSON or Sparkplug B), ``[opcua]``, ``[modbus]``,
``[web]``, ``[metrics]``, ``[audit]``. The statistics go to stderr when polling ends
(``--duration`` elapsed, Ctrl-C, SIGTERM, or the reader of stdout went away), with a line per
face (backlog and drops). SIGHUP does not end it.

Exit 0 after ``--duration``, SIGTERM or a closed stdout; 130 after Ctrl-C; 1, with one line on
stderr saying what, when polling ended because something failed (it never ends early with 0);
2 for a bad configuration, a missing optional extra (the line names the pip install to run) or a
face that cannot start (a port taken, a certificate unreadable: the line names it).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
from collections.abc import Callable, Sequence
from typing import Any, TextIO

from plcstack.cli import plain_text, print_error
from plcstack.cli.faces import gateway_faces
from plcstack.cli.pcap import add_pcap_options, with_pcap
from plcstack.cli.reload import RuntimeControl
from plcstack.cli.run_options import add_run_options, overrides_of, seconds
from plcstack.cli.runtime import RuntimePoller, run_north
from plcstack.config import Config
from plcstack.config.overrides import Overrides, apply_overrides
from plcstack.errors import ConfigError
from plcstack.north.config import NorthConfig
from plcstack.north.face import Face
from plcstack.north.faces import missing, needs_of
from plcstack.north.influx import InfluxFormat
from plcstack.north.pipeline import North
from plcstack.north.stdout import StdoutLines
from plcstack.poll.config import PlcConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Scan
from plcstack.poll.sinks import FORMATS, each_line, jsonl_text
from plcstack.scale import cli as scale_cli


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


def _influx_text(north: NorthConfig, plcs: Sequence[PlcConfig]) -> Callable[[Sequence[Scan]], str]:
    """``--format influx``: the line protocol of ``plcs``, as ``[influx]`` lays it out."""
    return InfluxFormat(plcs, layout=north.influx_layout, measurement=north.influx_measurement).text


def _prepared(overrides: Overrides, args: argparse.Namespace, config: Config) -> Config:
    """What this run makes of a loaded file, at start and at every reload: the command line
    over it, and the part of the PLCs its ``--shard`` polls."""
    config = apply_overrides(config, overrides)
    poll = scale_cli.select(config.poll, args)
    return config if poll is config.poll else dataclasses.replace(config, poll=poll)


async def run_poll(args: argparse.Namespace, out: TextIO | None = None) -> int:
    out = out if out is not None else sys.stdout
    # the scale-out options, None where a caller's namespace (not the parser's) has none
    args = argparse.Namespace(**{"shard": None, "mqtt": None, "nats": None, **vars(args)})
    # read once; relative file paths in [mqtt] are taken relative to the TOML file
    try:
        control = RuntimeControl.load(
            args.config, functools.partial(_prepared, overrides_of(args), args)
        )
    except ConfigError:
        raise
    except ValueError as exc:  # --shard and --mqtt, a bad --shard
        print_error(f"poll: {exc}")
        return 2
    whole = control.config
    config, north_config = whole.poll, whole.north
    needs = needs_of(north_config)
    if args.mqtt is not None:
        needs.append(("--mqtt (scale-out)", "aiomqtt", "scale"))
    if args.nats is not None:
        needs.append(("--nats (scale-out)", "nats", "scale"))
    problem = missing(needs)
    if problem is not None:
        print_error(f"poll: {problem}")
        return 2
    try:
        worker = scale_cli.make_worker(config, args)  # --mqtt: one worker of a cluster
    except ValueError as exc:
        print_error(f"poll: {exc}")
        return 2
    # every URL and address checked here, before anything is sent
    poller: RuntimePoller = worker if worker is not None else Poller(config)
    # the lines of the file's PLCs (float32 tags at float32 precision): made again from the
    # PLCs of a reloaded file
    text_of: Callable[[Sequence[PlcConfig]], Callable[[Sequence[Scan]], str]] | None = None
    if args.format == "influx":
        text_of = functools.partial(_influx_text, north_config)
    elif args.format == "jsonl":
        text_of = jsonl_text
    elif args.format != "none":
        line = FORMATS[args.format]
        text_of = lambda _: functools.partial(each_line, line)  # noqa: E731
    faces: list[Face] = []
    if text_of is not None:
        faces.append(StdoutLines(text_of(config.plcs), out, remake=text_of))
    # every face of the file, built
    north = North(poller, north_config, faces=faces, control=control)
    # [[gateway]]: the native faces, on the PLCs' connections (not a scale-out worker's);
    # none in the file is none yet: a reload may add some
    natives = None
    if isinstance(poller, Poller):
        natives = gateway_faces(whole.gateway, poller.client, north.writes)
    return await run_north(
        "poll",
        control,
        poller,
        north,
        duration=getattr(args, "duration", None),
        stats_every=getattr(args, "stats_every", None),
        out=out,
        natives=natives,
    )
