"""``plcstack tags``: tag lists from engineering tools in and out.

    plcstack tags import kepware FILE.csv --plc NAME --url URL   Kepware CSV -> [[plc]] TOML
    plcstack tags import gx FILE.csv --plc NAME --url URL        GX device comments -> TOML
    plcstack tags export CONFIG.toml --format kepware [--plc N]  a PLC's tags -> Kepware CSV
    plcstack tags list CONFIG.toml [--plc NAME]                  the tags as JSON lines

Output goes to stdout only once the whole file converted; a row that cannot be converted is one
line on stderr, FILE:ROW, the column and why, and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, TextIO

from plcstack.cli import plain_text
from plcstack.config import load_config
from plcstack.errors import AddressError
from plcstack.poll.config import PlcConfig, PollConfig
from plcstack.tags import TagListError, read_gx, read_kepware, to_toml, write_kepware
from plcstack.tags.gx import Skipped
from plcstack.values import UINT16, value_type


def register(subparsers: Any) -> None:
    tags = subparsers.add_parser(
        "tags",
        help="import tag lists (Kepware CSV, GX device comments) and export Kepware CSV",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = tags.add_subparsers(dest="tags_command", required=True, metavar="ACTION")
    imports = actions.add_parser("import", help="a tag list file -> a [[plc]] TOML block")
    formats = imports.add_subparsers(dest="tags_format", required=True, metavar="FORMAT")
    kepware = formats.add_parser("kepware", help="Kepware (KEPServerEX) tag CSV")
    gx = formats.add_parser("gx", help="GX Developer / GX Works2 device comment CSV")
    for parser in (kepware, gx):
        parser.add_argument("file", help="the CSV file, as the tool wrote it")
        parser.add_argument("--plc", required=True, help="name of the PLC in the config")
        parser.add_argument(
            "--url", required=True, help="the PLC's URL, e.g. e71+tcp://10.0.0.5:5000"
        )
    gx.add_argument(
        "--type",
        default="uint16",
        help="value type of word devices (default uint16); bit devices are bool",
    )
    gx.add_argument(
        "--skip-unsupported",
        action="store_true",
        help="leave out devices the PLC family cannot hold (each named on stderr) "
        "instead of refusing the file",
    )
    kepware.set_defaults(func=run_import_kepware)
    gx.set_defaults(func=run_import_gx)

    export = actions.add_parser("export", help="a PLC's tags of a config -> Kepware CSV")
    export.add_argument("config", help="TOML config file")
    export.add_argument("--format", choices=["kepware"], required=True, help="file format")
    export.add_argument("--plc", help="the PLC to export (needed when the config has several)")
    export.set_defaults(func=run_export)

    listing = actions.add_parser("list", help="the tags of a config as JSON lines")
    listing.add_argument("config", help="TOML config file")
    listing.add_argument("--plc", help="only this PLC's tags")
    listing.set_defaults(func=run_list)


def _read(path: str) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise TagListError(f"cannot read {path}: {exc.strerror or exc}") from None


async def run_import_kepware(args: argparse.Namespace, out: TextIO | None = None) -> int:
    imported = read_kepware(_read(args.file), args.file, plc=args.plc, url=args.url)
    text = to_toml(imported)
    (out or sys.stdout).write(text)
    return 0


async def run_import_gx(args: argparse.Namespace, out: TextIO | None = None) -> int:
    try:
        word_type = value_type(args.type) if args.type != "uint16" else UINT16
    except AddressError as exc:
        raise AddressError(f"--type: {exc.message}") from None

    def report(skip: Skipped) -> None:
        print(
            f"plcstack: skipped {args.file}:{skip.line}: {skip.device}: {skip.why}", file=sys.stderr
        )

    imported = read_gx(
        _read(args.file),
        args.file,
        plc=args.plc,
        url=args.url,
        word_type=word_type,
        skip_unsupported=args.skip_unsupported,
        skipped=report,
    )
    text = to_toml(imported)
    (out or sys.stdout).write(text)
    return 0


def _plcs(config: PollConfig, name: str | None, source: str) -> list[PlcConfig]:
    if name is None:
        return list(config.plcs)
    chosen = [plc for plc in config.plcs if plc.name == name]
    if not chosen:
        names = ", ".join(plc.name for plc in config.plcs)
        raise TagListError(f"{source}: no PLC named {name!r} (PLCs: {names})")
    return chosen


async def run_export(args: argparse.Namespace, out: TextIO | None = None) -> int:
    config = load_config(args.config).poll
    plcs = _plcs(config, args.plc, args.config)
    if len(plcs) > 1:
        names = ", ".join(plc.name for plc in plcs)
        raise TagListError(
            f"{args.config} has {len(plcs)} PLCs ({names}); a Kepware CSV holds one: "
            "choose it with --plc"
        )
    text = write_kepware(plcs[0], config.groups)
    (out or sys.stdout).write(text)
    return 0


async def run_list(args: argparse.Namespace, out: TextIO | None = None) -> int:
    config = load_config(args.config).poll
    lines = []
    for plc in _plcs(config, args.plc, args.config):
        for tag in plc.tags:
            scale = tag.scale
            record = {
                "plc": plc.name,
                "tag": tag.name,
                "address": tag.address,
                "type": tag.type.name,
                "count": tag.count,
                "group": tag.group,
                "interval": config.groups[tag.group],
                "writable": tag.writable,
                "scale": (
                    None
                    if scale is None
                    else [scale.raw_lo, scale.raw_hi, scale.eng_lo, scale.eng_hi]
                ),
                "unit": tag.unit,
                "description": tag.description,
            }
            lines.append(json.dumps(record, ensure_ascii=False) + "\n")
    (out or sys.stdout).write("".join(lines))
    return 0
