"""Scale-out: shard a fleet of PLCs over worker processes (docs/scale-out.md).

* :mod:`plcstack.scale.hrw` -- rendezvous hashing: which worker polls which PLC; static shards.
"""

from plcstack.scale.hrw import (
    ShardSpec,
    assign,
    index_from_hostname,
    owner,
    parse_shard,
    shard_config,
    weight,
)

__all__ = [
    "ShardSpec",
    "assign",
    "index_from_hostname",
    "owner",
    "parse_shard",
    "shard_config",
    "weight",
]
