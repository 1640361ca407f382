"""``plcstack read`` and ``plcstack write``: one-shot access to any PLC by URL."""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

from plcstack.clients.base import Client
from plcstack.errors import AddressError
from plcstack.poll.values import DataType, Scalar, WordOrder, default_word_order
from plcstack.url import connect, parse_url

_TYPES = [t.value for t in DataType]
_TYPE_HELP = (
    "value type (default raw: one value per point). int32/uint32/float32 span two words; "
    "COUNT then counts values, not points"
)


def register(subparsers: Any) -> None:
    read = subparsers.add_parser("read", help="read points from a PLC")
    read.add_argument("url", help="PLC URL, e.g. e71+tcp://127.0.0.1:5000 or s5lan://host:5010")
    read.add_argument("address", help="first address, e.g. D100, M0, DB10.DW5, MB100")
    read.add_argument("count", nargs="?", type=int, default=1, help="number of points (default 1)")
    read.add_argument("--json", action="store_true", help='print {"address": ..., "values": [...]}')
    _add_common_options(read)
    read.set_defaults(func=run_read)

    write = subparsers.add_parser("write", help="write points to a PLC")
    write.add_argument("url", help="PLC URL")
    write.add_argument("address", help="first address")
    write.add_argument(
        "values",
        nargs="+",
        help="values: integers (123, -5, 0x1F), true/false for bits, decimals with --type float32",
    )
    _add_common_options(write)
    write.set_defaults(func=run_write)


def _add_common_options(parser: argparse.ArgumentParser) -> None:
    """Options ``read`` and ``write`` share: the deadline and how values map onto points."""
    parser.add_argument("--timeout", type=float, default=None, help="request deadline in seconds")
    parser.add_argument("--type", choices=_TYPES, default="raw", help=_TYPE_HELP)
    parser.add_argument(
        "--word-order",
        choices=("big", "little"),
        default=None,
        help="order of the words of a multi-word type (default: little for E71, big for S5)",
    )


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


class _Layout:
    """How ``--type`` maps values onto the points of ``address`` (the poller's tag types)."""

    def __init__(self, plc: Client, args: argparse.Namespace) -> None:
        self.dtype = DataType(args.type)
        area, _ = plc.locate(args.address)  # checks the address; nothing is sent
        self.bits = plc.point_bits(area)
        try:
            self.dtype.check_area(self.bits, f"{args.address} as {self.dtype.value}")
        except AddressError as exc:
            raise exc.bind(plc=plc.name) from None
        self.per = self.dtype.points_per_value(self.bits)
        self.order = (
            WordOrder(args.word_order)
            if args.word_order
            else default_word_order(parse_url(args.url).scheme)
        )

    def decode(self, points: list[int] | list[bool], count: int) -> list[Scalar]:
        n = self.per
        return [self.dtype.decode(points[i * n : (i + 1) * n], self.bits, self.order)
                for i in range(count)]  # fmt: skip

    def encode(self, texts: list[str]) -> list[int | bool]:
        out: list[int | bool] = []
        for text in texts:
            value: Scalar = (
                _parse_float(text) if self.dtype is DataType.FLOAT32 else parse_value(text)
            )
            out += self.dtype.encode(value, self.bits, self.order)
        return out


def _parse_float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise AddressError(f"value {text!r} is not a number") from None


def _json_value(value: Scalar) -> Scalar | None:
    # NaN and infinities are not JSON; say "no number" rather than emit invalid output
    return None if isinstance(value, float) and not math.isfinite(value) else value


async def run_read(args: argparse.Namespace) -> int:
    # No eager open (``async with`` would connect first): the client checks the address before
    # it connects, so a typo is exit 2 even when the PLC is unreachable, and nothing is sent.
    plc = connect(args.url, **_options(args))
    try:
        if args.type == "raw":
            values: list[Scalar] = list(await plc.read(args.address, args.count))
        else:
            layout = _Layout(plc, args)
            points = await plc.read(args.address, args.count * layout.per)
            values = layout.decode(points, args.count)
    finally:
        await plc.aclose()
    if args.json:
        print(json.dumps({"address": args.address, "values": [_json_value(v) for v in values]}))
    else:
        print(f"{args.address}: " + " ".join(str(v) for v in values))
    return 0


async def run_write(args: argparse.Namespace) -> int:
    plc = connect(args.url, **_options(args))
    try:
        if args.type == "raw":
            points: list[int | bool] = [parse_value(v) for v in args.values]
        else:
            layout = _Layout(plc, args)
            try:
                points = layout.encode(args.values)
            except AddressError as exc:
                raise exc.bind(plc=plc.name, request=f"write {args.address}") from None
        await plc.write(args.address, points)
    finally:
        await plc.aclose()
    print(f"{args.address}: wrote {len(args.values)} value(s)")
    return 0
