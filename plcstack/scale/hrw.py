"""Rendezvous (highest-random-weight) hashing: which worker polls which PLC.

Every worker computes the same answer from the same inputs, with no coordination: a PLC belongs to
the worker whose ``weight(worker, plc)`` is highest. When a worker joins, it takes only the PLCs
for which it now scores highest (about 1/N of the fleet) and nothing else moves; when it leaves,
only its own PLCs move, spread over the others. A modulo hash would move almost every PLC.

The weight is the first 8 bytes of BLAKE2b over ``worker``, a NUL and ``plc`` (UTF-8), read big
endian. It must never change between releases: workers of two versions must agree on the owner of
every PLC, so ``tests/test_scale_hrw.py`` pins golden values.
"""

from __future__ import annotations

import dataclasses
import hashlib
import re
import socket
from collections.abc import Iterable

from plcstack.poll.config import PollConfig

__all__ = [
    "ShardSpec",
    "assign",
    "index_from_hostname",
    "owner",
    "parse_shard",
    "shard_config",
    "shard_worker",
    "weight",
]


def weight(worker: str, plc: str) -> int:
    """The score of ``worker`` for ``plc``: a 64-bit integer, the same on every machine."""
    digest = hashlib.blake2b(
        worker.encode() + b"\0" + plc.encode(), digest_size=8, person=b"plcstack-hrw"
    ).digest()
    return int.from_bytes(digest, "big")


def owner(plc: str, workers: Iterable[str]) -> str | None:
    """The worker that polls ``plc`` among ``workers`` (None when there are none).

    Ties (astronomically unlikely with 64 bits) go to the smaller worker name, so the answer
    never depends on the order of ``workers``.
    """
    best: tuple[int, str] | None = None
    for worker in workers:
        score = weight(worker, plc)
        if best is None or score > best[0] or (score == best[0] and worker < best[1]):
            best = (score, worker)
    return None if best is None else best[1]


def assign(plcs: Iterable[str], workers: Iterable[str]) -> dict[str, str]:
    """``{plc: worker}`` for every PLC (empty when there is no worker)."""
    pool = sorted(set(workers))
    if not pool:
        return {}
    return {plc: owner(plc, pool) or pool[0] for plc in plcs}


def shard_worker(index: int) -> str:
    """The worker name static shard ``index`` scores under (``--shard i/N``)."""
    return f"shard-{index}"


class ShardSpec:
    """``--shard i/N``: this process is shard ``index`` of ``count`` (0 <= index < count)."""

    __slots__ = ("count", "index")

    def __init__(self, index: int, count: int) -> None:
        if count < 1:
            raise ValueError(f"shard count must be at least 1, not {count}")
        if not 0 <= index < count:
            raise ValueError(f"shard index must be 0..{count - 1}, not {index}")
        self.index = index
        self.count = count

    def owns(self, plc: str) -> bool:
        workers = [shard_worker(i) for i in range(self.count)]
        return owner(plc, workers) == shard_worker(self.index)

    def __repr__(self) -> str:
        return f"ShardSpec({self.index}/{self.count})"


_ORDINAL = re.compile(r"(\d+)$")


def index_from_hostname(hostname: str | None = None) -> int:
    """The trailing number of a host name: ``plcstack-2`` -> 2 (Kubernetes StatefulSet pods are
    named ``<set>-<ordinal>``). Raises ValueError when the name does not end in digits."""
    name = hostname if hostname is not None else socket.gethostname()
    short = name.split(".", 1)[0]
    match = _ORDINAL.search(short)
    if match is None:
        raise ValueError(f"host name {name!r} does not end in a number (like plcstack-2)")
    return int(match.group(1))


def parse_shard(text: str, *, hostname: str | None = None) -> ShardSpec:
    """Parse ``i/N``; ``i`` may be ``host`` for the host name's trailing number."""
    index_text, sep, count_text = text.partition("/")
    if not sep:
        raise ValueError(f"--shard takes INDEX/COUNT (like 0/3 or host/3), not {text!r}")
    try:
        count = int(count_text)
    except ValueError:
        raise ValueError(f"--shard {text!r}: COUNT must be a number") from None
    if index_text.strip().lower() == "host":
        index = index_from_hostname(hostname)
    else:
        try:
            index = int(index_text)
        except ValueError:
            raise ValueError(f"--shard {text!r}: INDEX must be a number or 'host'") from None
    return ShardSpec(index, count)


def shard_config(config: PollConfig, index: int, count: int) -> PollConfig:
    """The part of ``config`` that static shard ``index`` of ``count`` polls (same settings)."""
    spec = ShardSpec(index, count)
    return dataclasses.replace(config, plcs=tuple(p for p in config.plcs if spec.owns(p.name)))
