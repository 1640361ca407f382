"""``plcstack read`` and ``plcstack write``: one-shot access to any PLC by URL."""

from __future__ import annotations

import argparse
import json
import math
import re
from typing import Any

from plcstack.cli.pcap import add_pcap_options, with_pcap
from plcstack.clients import connect
from plcstack.errors import AddressError
from plcstack.output import float32_short, json_safe
from plcstack.values import TYPES, Scalar, WordOrder, value_type

_TYPES = f"value type (default raw: one value per point): {', '.join(TYPES)}, string:N[:space]. "
_READ_TYPE_HELP = (
    _TYPES + "Types wider than a point (int32, float32, kg, bcd32, strings) span several; COUNT "
    "then counts values, not points. A bit: ADDRESS D100.3, DB10.DW5.3 or M10.3 with --type bool"
)
_WRITE_TYPE_HELP = (
    _TYPES + "Each VALUE is one value of the type; types wider than a point (int32, float32, "
    "kg, bcd32, strings) fill several points each. A bit of a word is not written (that would "
    "be a read-modify-write racing the PLC program): write the whole word"
)


#: what a negative value looks like on the command line: -5, -0x1F, -2.5e3, -.5, -inf, -nan
_NEGATIVE_VALUE = re.compile(r"^-(\d|\.\d|inf(inity)?$|nan$)", re.IGNORECASE)


_READ_DESCRIPTION = """\
plcstack read URL ADDRESS [COUNT]: read COUNT points (values, with --type) from ADDRESS on.

The line is ADDRESS: v1 v2 ... (--json: one JSON object). The address is checked by the rules
of the PLC family the URL names before anything is sent: MELSEC D100, M0, X1F (hexadecimal),
S5 DB10.DW5, MB100, IB0 (plcstack docs e71, plcstack docs s5-addresses). Against the
simulators (plcstack sim e71 & plcstack sim s5lan &):

  plcstack read e71+tcp://127.0.0.1:5000 D100 4
  plcstack read s5lan://127.0.0.1:5010 DB10.DW0 2 --type float32

Exit 0; 1 when the PLC side failed (error code, timeout, unreachable); 2 for bad usage. A
failure is one line on stderr."""

_WRITE_DESCRIPTION = """\
plcstack write URL ADDRESS VALUE...: write the values to the points from ADDRESS on.

Prints ADDRESS: wrote N value(s) once the PLC confirmed the write. A write is never retried:
after a timeout or a lost connection the error line says whether it may have been executed.
Against the simulators (plcstack sim e71 & plcstack sim s5lan &):

  plcstack write e71+tcp://127.0.0.1:5000 D100 1 2 -3
  plcstack write s5lan://127.0.0.1:5010 DB10.DW0 12.5 --type float32

Exit 0; 1 when the PLC side failed; 2 for bad usage, found before anything is sent."""


def register(subparsers: Any) -> None:
    read = subparsers.add_parser(
        "read",
        help="read points from a PLC",
        description=_READ_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    read.add_argument("url", help="PLC URL, e.g. e71+tcp://127.0.0.1:5000 or s5lan://host:5010")
    read.add_argument("address", help="first address, e.g. D100, M0, DB10.DW5, MB100")
    read.add_argument("count", nargs="?", type=int, default=1, help="number of points (default 1)")
    read.add_argument("--json", action="store_true", help='print {"address": ..., "values": [...]}')
    _add_common_options(read, _READ_TYPE_HELP)
    add_pcap_options(read)
    read.set_defaults(func=with_pcap(run_read))

    write = subparsers.add_parser(
        "write",
        help="write points to a PLC",
        description=_WRITE_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    write.add_argument("url", help="PLC URL")
    write.add_argument("address", help="first address")
    write.add_argument(
        "values",
        nargs="+",
        help="values: integers (123, -5, 0x1F), true/false for bits, decimals with --type float32",
    )
    _add_common_options(write, _WRITE_TYPE_HELP)
    # argparse takes "-2.5e3" or "-inf" for an option (its own rule knows only -5 and -.5);
    # no option of ``write`` starts with a digit, a dot or these words, so values they are
    write._negative_number_matcher = _NEGATIVE_VALUE
    add_pcap_options(write)
    write.set_defaults(func=with_pcap(run_write))


def _add_common_options(parser: argparse.ArgumentParser, type_help: str) -> None:
    """Options ``read`` and ``write`` share: the deadline and how values map onto points."""
    parser.add_argument("--timeout", type=float, default=None, help="request deadline in seconds")
    parser.add_argument("--type", type=_type_name, default="raw", metavar="TYPE", help=type_help)
    parser.add_argument(
        "--word-order",
        choices=("big", "little"),
        default=None,
        help="order of the words of a multi-word type (default: little for E71, big for S5)",
    )


def parse_value(text: str) -> int | bool:
    """CLI value syntax: ``true``/``false``/``on``/``off`` are bits, anything else an integer;
    an integral decimal (``1201.0``, ``1.2e3``) is that integer, as every north side's write
    grammar takes it, so a value copied from a JSON producer or a spreadsheet works here too."""
    low = text.lower()
    if low in ("true", "on"):
        return True
    if low in ("false", "off"):
        return False
    try:
        return int(text, 0)
    except ValueError:
        pass
    try:
        number = float(text)
    except ValueError:
        number = math.nan
    if number.is_integer():
        return int(number)
    if math.isfinite(number):  # 12.5: a decimal is a type of several points, not a raw point
        raise AddressError(
            f"value {text!r} is not an integer or true/false; "
            "a decimal needs a type: --type float32 (two points per value)"
        )
    raise AddressError(f"value {text!r} is not an integer or true/false")


def shown(value: object) -> str:
    """``value`` for a terminal: a text's control characters (a KC word of two raw bytes, a
    string with NULs) escaped as ``\\x01``, so the output neither moves the cursor nor hides
    characters; printable text, numbers and bits as they are."""
    text = str(value)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _options(args: argparse.Namespace) -> dict[str, Any]:
    return {"timeout": args.timeout} if args.timeout is not None else {}


def _type_name(text: str) -> str:
    try:
        value_type(text)  # an unknown name is a usage error (exit 2) naming the known types
    except AddressError as exc:
        raise argparse.ArgumentTypeError(exc.message) from None
    return text


def _order(args: argparse.Namespace) -> WordOrder | None:
    return WordOrder(args.word_order) if args.word_order else None


def _text_value(text: str, kind: str) -> object:
    """CLI value syntax for a typed write: numbers for numeric types, the text itself for
    strings, ``12,255`` for KY, true/false for bits."""
    if kind == "float":
        return _parse_float(text)
    if kind == "text":
        return text
    if kind == "bytes":
        parts = text.split(",")
        try:
            return tuple(int(p, 0) for p in parts)
        except ValueError:
            raise AddressError(f"value {text!r} is not two bytes like 12,255") from None
    return parse_value(text)


def _parse_float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise AddressError(f"value {text!r} is not a number") from None


async def run_read(args: argparse.Namespace) -> int:
    # No eager open (``async with`` would connect first): the client checks the address before
    # it connects, so a typo is exit 2 even when the PLC is unreachable, and nothing is sent.
    plc = connect(args.url, **_options(args))
    try:
        if args.type == "raw":
            values: list[Scalar] = list(await plc.read(args.address, args.count))
        else:
            vtype = value_type(args.type)
            values = await plc.read_as(args.address, vtype, args.count, word_order=_order(args))
            if vtype.kind == "float" and vtype.bits == 32:
                values = [float32_short(v) if isinstance(v, float) else v for v in values]
    finally:
        await plc.aclose()
    if args.json:
        print(json.dumps({"address": args.address, "values": json_safe(values)}))
    else:
        print(f"{args.address}: " + " ".join(shown(v) for v in values))
    return 0


async def run_write(args: argparse.Namespace) -> int:
    plc = connect(args.url, **_options(args))
    try:
        # a value that does not parse is reported like any other refusal: with the PLC and
        # the request, so the line says which of several scripted writes it was
        try:
            if args.type == "raw":
                points: list[int | bool] = [parse_value(v) for v in args.values]
            else:
                vtype = value_type(args.type)
                typed = [_text_value(v, vtype.kind) for v in args.values]
        except AddressError as exc:
            raise exc.bind(plc=plc.name, request=f"write {args.address}") from None
        if args.type == "raw":
            await plc.write(args.address, points)
        else:
            await plc.write_as(args.address, vtype, typed, word_order=_order(args))
    finally:
        await plc.aclose()
    print(f"{args.address}: wrote {len(args.values)} value(s)")
    return 0
