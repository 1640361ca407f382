"""What ``serve opcua`` and ``serve modbus`` share: the one runtime, with their face on.

Both are shortcuts of ``plcstack poll CONFIG --format none`` that make sure their face runs
(with its defaults when the file has no table for it): the same runtime, the same poller with
one connection per PLC, and every other face the file configures (``[mqtt]``, ``[web]``,
``[metrics]``, ...) on the same scans. Written once, so the two servers cannot drift apart in
what their options mean or in what a write's audit line holds.
"""

from __future__ import annotations

import argparse

from plcstack.cli import print_error
from plcstack.cli.runtime import run_north
from plcstack.north.config import NorthConfig
from plcstack.north.faces import missing, needs_of
from plcstack.north.pipeline import North
from plcstack.poll.config import PollConfig
from plcstack.poll.engine import Poller

__all__ = ["run_served"]


async def run_served(
    args: argparse.Namespace, command: str, config: PollConfig, north_config: NorthConfig
) -> int:
    """The runtime with ``north_config`` (the served face's table already in it, the
    command line's overrides applied): every face of the file, no lines on stdout."""
    problem = missing(needs_of(north_config))
    if problem is not None:
        print_error(f"{command}: {problem}")
        return 2
    poller = Poller(config)  # every URL and address checked before anything is sent
    north = North(poller, north_config)
    return await run_north(command, args.config, poller, north, duration=args.duration)
