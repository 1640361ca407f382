"""The options of every command that runs the poller and its faces, defined once.

``--duration`` (stop after SECONDS), ``--metrics-port`` and ``--web-port`` (over the file's
``[metrics]`` / ``[web]`` port) mean the same for ``poll``, ``serve opcua`` and ``serve modbus``
and are checked the same way, by argparse, before the file is read: a bad value is one line,
exit 2. The ports become :class:`~plcstack.config.overrides.Overrides`, which
:func:`~plcstack.config.overrides.apply_overrides` applies to the file (and to every file a
reload reads).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Collection

from plcstack.config.overrides import Overrides

__all__ = ["add_run_options", "overrides_of", "port", "seconds"]


def seconds(text: str) -> float:
    """An argparse type: a finite number of seconds greater than 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be greater than 0, not {text}")
    return value


def port(text: str) -> int:
    """An argparse type: a TCP port 0..65535 (0: any free port)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be 0..65535, not {value}")
    return value


def add_run_options(
    parser: argparse.ArgumentParser, *, faces: Collection[str] = ("metrics", "web")
) -> None:
    """``--duration`` and the port override of each face in ``faces`` the command runs."""
    parser.add_argument(
        "--duration",
        type=seconds,
        default=None,
        metavar="SECONDS",
        help="stop after SECONDS (default: run until Ctrl-C or SIGTERM)",
    )
    if "metrics" in faces:
        parser.add_argument(
            "--metrics-port",
            type=port,
            default=None,
            metavar="PORT",
            help="serve /metrics and /healthz on PORT (0: any free port), over the port of"
            " [metrics] listen (host from it, default 127.0.0.1)",
        )
    if "web" in faces:
        parser.add_argument(
            "--web-port",
            type=port,
            default=None,
            metavar="PORT",
            help="serve the web console and REST API on PORT (0: any free port), over the port"
            " of [web] listen",
        )


def overrides_of(args: argparse.Namespace) -> Overrides:
    """The overrides of a command line parsed with :func:`add_run_options`."""
    # a command without one of the options, or arguments built by hand, leave it unset
    return Overrides(
        web_port=getattr(args, "web_port", None), metrics_port=getattr(args, "metrics_port", None)
    )
