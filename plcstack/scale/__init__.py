"""Scale-out: shard a fleet of PLCs over worker processes (docs/scale-out.md).

* :mod:`plcstack.scale.hrw` -- rendezvous hashing: which worker polls which PLC; static shards.
* :mod:`plcstack.scale.presence` -- live workers from an MQTT broker (retained status, Will).
* :mod:`plcstack.scale.lease` -- leases with a fencing revision in NATS JetStream KV.
* :mod:`plcstack.scale.worker` -- the worker loop: start and stop PLCs as ownership changes.
* :mod:`plcstack.scale.cli` -- ``plcstack poll --shard i/N`` and ``--mqtt/--nats``.

Only :mod:`hrw` is imported here: the others need the optional extra ``plcstack[scale]``
(aiomqtt, nats-py).
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
