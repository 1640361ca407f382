"""A minimal Sparkplug B host: watch one edge node and print its births and data, decoded.

A host that joins after the node was born has missed the NBIRTH that declares the metrics, so
(as a Sparkplug host application does) on the first data without a birth it asks the node for
a rebirth with an NCMD ``Node Control/Rebirth = true``, and it prints from the next NBIRTH on:
one line per message with its type, device, ``seq`` and every metric (value, and for births
the datatype).

    plcstack poll sparkplug.toml --format none &        # [mqtt] mode = "sparkplug"
    python examples/sparkplug_host.py mqtt://127.0.0.1:1883 plant1 line1 3

Arguments: broker URL, group id, edge node id (the poller's client_id), how many messages to
print (default 3). Needs the ``sparkplug`` extra (aiomqtt, protobuf).
"""

from __future__ import annotations

import asyncio
import sys
import time
from urllib.parse import urlsplit

import aiomqtt

from plcstack.north.sparkplug_pb import DATATYPES, Metric, Payload


def rebirth_request() -> bytes:
    """The NCMD payload that asks an edge node for NBIRTH and all DBIRTHs again."""
    payload = Payload(timestamp=int(time.time() * 1000))
    payload.metrics.append(Metric(name="Node Control/Rebirth", datatype=11, boolean_value=True))
    data: bytes = payload.SerializeToString()
    return data


def describe(kind: str, device: str, payload: Payload) -> str:
    """``DDATA line1/press1 seq 2: strokes=1200, force=12.5``; births name each datatype."""
    names = {code: name for name, code in DATATYPES.items()}
    parts = []
    for metric in payload.metrics:
        field = metric.WhichOneof("value")
        value = None if metric.is_null or field is None else getattr(metric, field)
        declared = f" ({names.get(metric.datatype, metric.datatype)})" if "BIRTH" in kind else ""
        parts.append(f"{metric.name}={value}{declared}")
    return f"{kind} {device} seq {payload.seq}: {', '.join(parts)}"


async def main(url: str, group: str, node: str, count: int) -> None:
    where = urlsplit(url)
    async with aiomqtt.Client(where.hostname or "127.0.0.1", where.port or 1883) as client:
        await client.subscribe(f"spBv1.0/{group}/+/{node}/#")
        born, asked, shown = False, False, 0
        async for message in client.messages:
            levels = str(message.topic).split("/")
            kind, device = levels[2], "/".join(levels[3:])
            born = born or kind == "NBIRTH"
            if not born:  # data of a node born before we came: ask for its births, once
                if not asked:
                    await client.publish(f"spBv1.0/{group}/NCMD/{node}", rebirth_request())
                    asked = True
                continue
            if kind == "NCMD":
                continue
            assert isinstance(message.payload, bytes)
            payload = Payload()
            payload.ParseFromString(message.payload)
            print(describe(kind, device, payload), flush=True)
            shown += 1
            if shown == count:
                return


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    count = int(sys.argv[4]) if len(sys.argv) > 4 else 3
    asyncio.run(main(sys.argv[1], sys.argv[2], sys.argv[3], count))
