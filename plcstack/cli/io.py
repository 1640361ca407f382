"""``plcstack read`` and ``plcstack write``: one-shot access to any PLC by URL."""

from __future__ import annotations

import argparse
import json
from typing import Any

from plcstack.errors import AddressError
from plcstack.url import connect


def register(subparsers: Any) -> None:
    read = subparsers.add_parser("read", help="read points from a PLC")
    read.add_argument("url", help="PLC URL, e.g. e71+tcp://127.0.0.1:5000 or s5lan://host:5010")
    read.add_argument("address", help="first address, e.g. D100, M0, DB10.DW5, MB100")
    read.add_argument("count", nargs="?", type=int, default=1, help="number of points (default 1)")
    read.add_argument("--json", action="store_true", help='print {"address": ..., "values": [...]}')
    read.add_argument("--timeout", type=float, default=None, help="request deadline in seconds")
    read.set_defaults(func=run_read)

    write = subparsers.add_parser("write", help="write points to a PLC")
    write.add_argument("url", help="PLC URL")
    write.add_argument("address", help="first address")
    write.add_argument(
        "values", nargs="+", help="values: integers (123, -5, 0x1F) or true/false for bits"
    )
    write.add_argument("--timeout", type=float, default=None, help="request deadline in seconds")
    write.set_defaults(func=run_write)


def parse_value(text: str) -> int | bool:
    """CLI value syntax: ``true``/``false``/``on``/``off`` are bits, anything else an integer."""
    low = text.lower()
    if low in ("true", "on"):
        return True
    if low in ("false", "off"):
        return False
    try:
        return int(text, 0)
    except ValueError:
        raise AddressError(f"value {text!r} is not an integer or true/false") from None


def _options(args: argparse.Namespace) -> dict[str, Any]:
    return {"timeout": args.timeout} if args.timeout is not None else {}


async def run_read(args: argparse.Namespace) -> int:
    # No eager open (``async with`` would connect first): the client checks the address before
    # it connects, so a typo is exit 2 even when the PLC is unreachable, and nothing is sent.
    plc = connect(args.url, **_options(args))
    try:
        values = await plc.read(args.address, args.count)
    finally:
        await plc.aclose()
    if args.json:
        print(json.dumps({"address": args.address, "values": list(values)}))
    else:
        print(f"{args.address}: " + " ".join(str(v) for v in values))
    return 0


async def run_write(args: argparse.Namespace) -> int:
    values = [parse_value(v) for v in args.values]
    plc = connect(args.url, **_options(args))
    try:
        await plc.write(args.address, values)
    finally:
        await plc.aclose()
    print(f"{args.address}: wrote {len(values)} value(s)")
    return 0
