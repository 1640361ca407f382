"""The scale-out options of ``plcstack poll`` (docs/scale-out.md).

Static: ``--shard i/N`` polls the PLCs that rendezvous hashing gives to shard ``i`` of ``N``;
``i`` may be ``host`` for the trailing number of the host name (Kubernetes StatefulSet pods are
named ``<set>-<ordinal>``). Every process reads the same config file.

Automatic: ``--mqtt URL`` makes this process one worker of a cluster: it announces itself on the
broker and polls the PLCs rendezvous hashing gives it among the live workers; with ``--nats URL``
every exclusive PLC also needs a lease, so no PLC ever has two pollers.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from typing import TYPE_CHECKING, Any

from plcstack.poll.config import PollConfig
from plcstack.scale.hrw import parse_shard, shard_config

if TYPE_CHECKING:
    from plcstack.scale.worker import Worker

__all__ = ["add_arguments", "make_worker", "select"]


def add_arguments(parser: Any) -> None:
    group = parser.add_argument_group("scale-out (plcstack docs scale-out)")
    group.add_argument(
        "--shard",
        metavar="I/N",
        default=None,
        help="poll only shard I of N (rendezvous hashing of PLC names; I may be 'host' for "
        "the host name's trailing number, as in a StatefulSet)",
    )
    group.add_argument(
        "--mqtt",
        metavar="URL",
        default=None,
        help="automatic mode: announce this worker on the MQTT broker mqtt://HOST:PORT and poll "
        "the PLCs it owns among the live workers",
    )
    group.add_argument(
        "--nats",
        metavar="URL",
        default=None,
        help="with --mqtt: take a lease per exclusive PLC in NATS JetStream KV nats://HOST:PORT "
        "(no PLC ever polled by two workers)",
    )
    group.add_argument(
        "--worker-id",
        default=None,
        help="this worker's unique name (default: the host name)",
    )
    group.add_argument("--cluster", default="plcstack", help="topic prefix and bucket name part")
    group.add_argument(
        "--lease-ttl",
        type=float,
        default=10.0,
        metavar="SECONDS",
        help="lease time: a dead worker's PLCs are polled again within about this (default 10)",
    )
    group.add_argument(
        "--lease-retry",
        type=float,
        default=None,
        metavar="SECONDS",
        help="how often to try a wanted lease (default min(ttl/4, 1))",
    )
    group.add_argument(
        "--keepalive", type=int, default=5, metavar="SECONDS", help="MQTT keepalive (default 5)"
    )
    group.add_argument(
        "--exclusive",
        action="append",
        default=None,
        metavar="PATTERN",
        help="PLC names (fnmatch) that need a lease; repeatable (default: every PLC)",
    )


def select(config: PollConfig, args: argparse.Namespace) -> PollConfig:
    """The part of ``config`` this process polls under ``--shard`` (all of it without)."""
    text = args.shard
    if text is None:
        return config
    if args.mqtt is not None:
        raise ValueError("--shard (static) and --mqtt (automatic) exclude each other")
    spec = parse_shard(text)
    return shard_config(config, spec.index, spec.count)


def make_worker(config: PollConfig, args: argparse.Namespace) -> Worker | None:
    """The automatic-mode worker for ``--mqtt`` (None without it); ValueError for bad options."""
    mqtt = args.mqtt
    if mqtt is None:
        if args.nats is not None:
            raise ValueError("--nats needs --mqtt (leases guard the PLCs presence assigns)")
        return None
    # imported here: aiomqtt and nats-py are the optional extra plcstack[scale]
    from plcstack.scale.presence import parse_mqtt_url
    from plcstack.scale.worker import Worker, WorkerOptions

    parse_mqtt_url(mqtt)
    worker = args.worker_id or socket.gethostname()
    options = WorkerOptions(
        worker=worker,
        mqtt=mqtt,
        nats=args.nats,
        cluster=args.cluster,
        lease_ttl=args.lease_ttl,
        retry=args.lease_retry,
        keepalive=args.keepalive,
        exclusive=tuple(args.exclusive) if args.exclusive else ("*",),
    )

    def event(text: str) -> None:
        stamp = time.strftime("%H:%M:%S", time.localtime())
        print(f"{stamp} worker {worker}: {text}", file=sys.stderr, flush=True)

    return Worker(config, options, on_event=event)
