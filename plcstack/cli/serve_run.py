"""What ``serve opcua`` and ``serve modbus`` share: the one runtime, with their face on.

Both are shortcuts of ``plcstack poll CONFIG --format none`` that make sure their face runs
(with its defaults when the file has no table for it): the same runtime, the same poller with
one connection per PLC, and every other face the file configures (``[mqtt]``, ``[web]``,
``[metrics]``, ..., the ``[[gateway]]`` faces on the PLCs' connections) on the same scans.
Written once, so the two servers cannot drift apart in what their options mean or in what a
write's audit line holds.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
from collections.abc import Callable

from plcstack.cli import print_error
from plcstack.cli.faces import gateway_faces
from plcstack.cli.reload import RuntimeControl
from plcstack.cli.run_options import overrides_of
from plcstack.cli.runtime import run_north
from plcstack.config import Config
from plcstack.config.overrides import apply_overrides
from plcstack.north.config import NorthConfig
from plcstack.north.faces import missing, needs_of
from plcstack.north.pipeline import North
from plcstack.poll.engine import Poller

__all__ = ["run_served"]

#: the served face's table put into a configuration's north side (its defaults when the file
#: has none)
WithFace = Callable[[NorthConfig], NorthConfig]


def _prepared(args: argparse.Namespace, with_face: WithFace, config: Config) -> Config:
    """What the run makes of a loaded file, at start and at every reload: the command line
    over it, the served face in it."""
    config = apply_overrides(config, overrides_of(args))
    return dataclasses.replace(config, north=with_face(config.north))


async def run_served(args: argparse.Namespace, command: str, with_face: WithFace) -> int:
    """The runtime with the file of ``args.config`` (the command line's overrides applied,
    the served face's table put in by ``with_face``): every face of the file, no lines on
    stdout."""
    control = RuntimeControl.load(args.config, functools.partial(_prepared, args, with_face))
    config, north_config = control.config.poll, control.config.north
    problem = missing(needs_of(north_config))
    if problem is not None:
        print_error(f"{command}: {problem}")
        return 2
    poller = Poller(config)  # every URL and address checked before anything is sent
    north = North(poller, north_config, control=control)
    # [[gateway]]: the native faces on the PLCs' connections, as plcstack poll runs them
    natives = gateway_faces(control.config.gateway, poller.client, north.writes)
    return await run_north(command, control, poller, north, duration=args.duration, natives=natives)
