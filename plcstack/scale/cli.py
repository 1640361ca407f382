"""The scale-out options of ``plcstack poll`` (see docs/scale-out.md).

``--shard i/N`` (static): this process polls the PLCs that rendezvous hashing gives to shard ``i``
of ``N``; ``i`` may be ``host`` for the trailing number of the host name (Kubernetes StatefulSet
pods are named ``<set>-<ordinal>``). Every process reads the same config file.
"""

from __future__ import annotations

import argparse
from typing import Any

from plcstack.poll.config import PollConfig
from plcstack.scale.hrw import parse_shard, shard_config

__all__ = ["add_arguments", "select"]


def add_arguments(parser: Any) -> None:
    group = parser.add_argument_group("scale-out (docs/scale-out.md)")
    group.add_argument(
        "--shard",
        metavar="I/N",
        default=None,
        help="poll only shard I of N (rendezvous hashing of PLC names; I may be 'host' for "
        "the host name's trailing number, as in a StatefulSet)",
    )


def select(config: PollConfig, args: argparse.Namespace) -> PollConfig:
    """The part of ``config`` this process polls under ``--shard`` (all of it without)."""
    text = getattr(args, "shard", None)
    if text is None:
        return config
    spec = parse_shard(text)
    return shard_config(config, spec.index, spec.count)
