"""``plcstack wireshark DIR``: write the Lua dissectors for Wireshark and tshark into DIR.

One file per protocol: plcstack_melsec1e.lua (MELSEC E71 1E frame, binary and ASCII, TCP and
UDP), plcstack_s5lan.lua (S5-LAN-LINK), plcstack_as511.lua (AS511, serial captures and serial
device servers), plcstack_tanimk.lua (the Tani MK header; the FETCH/WRITE inside goes on to
Wireshark's own Sinec H1 dissector). Display filters: melsec1e, s5lan, as511, tanimk.

Wireshark loads them from its personal Lua plugins folder (Help > About Wireshark > Folders;
on Linux ~/.local/lib/wireshark/plugins), tshark also with -X lua_script:FILE:

  plcstack wireshark ~/.local/lib/wireshark/plugins
  tshark -r capture.pcapng -Y melsec1e

Each is registered on the simulators' default ports (E71 also 1280/1281); a PLC on another
port is found by Decode As (TCP/UDP port -> the protocol), or by the protocol's preference.
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path
from typing import Any

from plcstack.cli import UsageError, plain_text
from plcstack.wire.dissectors import write_dissectors


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "wireshark",
        help="write Lua dissectors for Wireshark and tshark into a folder",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "directory",
        metavar="DIR",
        help="where to write them (made if missing), e.g. ~/.local/lib/wireshark/plugins",
    )
    parser.set_defaults(func=run_wireshark)


def _write(directory: str) -> list[Path]:
    folder = Path(directory).expanduser()
    try:
        return write_dissectors(folder)
    except OSError as exc:
        raise UsageError(f"wireshark: cannot write into {folder}: {exc.strerror or exc}") from None


async def run_wireshark(args: argparse.Namespace) -> int:
    for path in await asyncio.to_thread(_write, args.directory):
        print(path)
    return 0
