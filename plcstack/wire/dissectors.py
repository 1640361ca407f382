"""``plcstack wireshark DIR``: Lua dissectors for Wireshark and tshark, one file per protocol.

The Lua code is kept beside this module (``wire/lua/``: what every dissector shares, then one
file per protocol); the tables it looks things up in (commands, devices, end codes, S5-LAN
areas and Err values, AS511 functions, block types) are generated here from the codecs' own
tables when the files are written, so a dissector can never name a code differently from the
codec that sends and parses it. Display filter names: ``melsec1e``, ``s5lan``, ``as511``,
``tanimk``; FETCH/WRITE inside the MK header goes on to Wireshark's own Sinec H1 dissector.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from importlib import metadata, resources
from pathlib import Path
from typing import Final

from plcstack.codecs.as511_jobs import FUNCTION_NAMES, OPERATING_MODES, SYSTEM_ADDRESS_NAMES
from plcstack.codecs.e71_buffers import FIXED_BUFFER_END_CODES
from plcstack.codecs.e71_command_events import CPU_MODELS, OPAQUE_COMMANDS
from plcstack.codecs.e71_devices import DEVICE_NAMES, Device
from plcstack.codecs.e71_end_codes import ABNORMAL_CODES, END_CODES
from plcstack.codecs.e71_framing import COMMAND_NAMES, REQUEST_RULES
from plcstack.codecs.s5lan import AREA_LETTERS, ERR_MEANINGS
from plcstack.sim.s5memory import BlockType

__all__ = ["DEFAULT_PORTS", "PROTOCOLS", "lua_source", "write_dissectors"]

#: the dissectors, by display filter name
PROTOCOLS: Final = ("melsec1e", "s5lan", "as511", "tanimk")

#: the ports each dissector is registered on until its preference says otherwise: the
#: simulators' defaults (``plcstack sim ...``), and for the E71 the manual's example ports
#: 500H and 501H. No protocol here has a port of its own: real modules use the port they are
#: configured with, found with "Decode As".
DEFAULT_PORTS: Final[Mapping[str, str]] = {
    "melsec1e": "5000,1280,1281",
    "s5lan": "5010",
    "as511": "5020",
    "tanimk": "5030",
}

LuaValue = bool | int | str | Sequence["LuaValue"]


def lua_string(text: str) -> str:
    """``text`` as a Lua 5.2 string literal: printable ASCII as it is, every other byte of its
    UTF-8 as a decimal escape (nothing a Lua parser could take for code)."""
    out = []
    for char in text:
        if char in '\\"':
            out.append("\\" + char)
        elif " " <= char <= "~":
            out.append(char)
        else:
            out.extend(f"\\{byte:03d}" for byte in char.encode())
    return '"' + "".join(out) + '"'


def lua_value(value: LuaValue) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return lua_string(value)
    return "{ " + ", ".join(lua_value(item) for item in value) + " }"


def lua_table(name: str, table: Mapping[int, LuaValue] | Sequence[LuaValue]) -> str:
    """``local NAME = {...}``: a mapping keyed by number (``[0x1a] = ...``) or a list."""
    lines = [f"local {name} = {{"]
    if isinstance(table, Mapping):
        lines += [f"    [{key:#04x}] = {lua_value(value)}," for key, value in table.items()]
    else:
        lines += [f"    {lua_value(value)}," for value in table]
    return "\n".join([*lines, "}"])


def tables(protocol: str) -> list[str]:
    """The generated part of a dissector: its tables, from the codecs."""
    ports = f"local DEFAULT_PORTS = {lua_string(DEFAULT_PORTS[protocol])}"
    if protocol == "melsec1e":
        return [
            lua_table("COMMANDS", COMMAND_NAMES),
            lua_table(
                "RULES",
                {
                    command: (
                        rule.base,
                        -1 if rule.count_at is None else rule.count_at,
                        rule.kind,
                        rule.per,
                        rule.packed,
                    )
                    for command, rule in REQUEST_RULES.items()
                },
            ),
            lua_table("OPAQUE", dict.fromkeys(sorted(OPAQUE_COMMANDS), True)),
            lua_table("DEVICES", {d.code: (d.letters, d.base, d.is_bit) for d in Device}),
            lua_table("DEVICE_NAMES", {d.code: f"{d.letters} ({DEVICE_NAMES[d]})" for d in Device}),
            lua_table("END_CODES", END_CODES),
            lua_table("FIXED_BUFFER_END_CODES", FIXED_BUFFER_END_CODES),
            lua_table("ABNORMAL_CODES", ABNORMAL_CODES),
            lua_table("CPU_MODELS", CPU_MODELS),
            ports,
        ]
    if protocol == "s5lan":
        return [
            lua_table("AREAS", {ord(letter): name for letter, name in AREA_LETTERS.items()}),
            lua_table("ERR_MEANINGS", ERR_MEANINGS),
            ports,
        ]
    if protocol == "as511":
        return [
            lua_table("FUNCTIONS", FUNCTION_NAMES),
            lua_table("BLOCK_TYPES", {int(block): block.name for block in BlockType}),
            lua_table("MODES", OPERATING_MODES),
            lua_table("SYSTEM_ADDRESSES", SYSTEM_ADDRESS_NAMES),
            ports,
        ]
    if protocol == "tanimk":
        return [ports]
    raise ValueError(f"no dissector named {protocol!r}; there are {', '.join(PROTOCOLS)}")


def _lua(name: str) -> str:
    return (resources.files(__package__ or "plcstack.wire") / "lua" / f"{name}.lua").read_text(
        encoding="utf-8"
    )


def lua_source(protocol: str) -> str:
    """The whole dissector of ``protocol``: a header, its tables, the shared code, its own."""
    try:
        version = metadata.version("plcstack")
    except metadata.PackageNotFoundError:  # a checkout that was never installed
        version = "(not installed)"
    header = (
        f"-- plcstack_{protocol}.lua: Wireshark/tshark dissector for {protocol}, written by\n"
        f"-- plcstack {version} (plcstack wireshark DIR). Its tables come from plcstack's\n"
        "-- codecs; write it again with the same command rather than editing it.\n"
    )
    return "\n\n".join([header, *tables(protocol), _lua("common"), _lua(protocol)])


def write_dissectors(directory: Path) -> list[Path]:
    """Write ``plcstack_PROTOCOL.lua`` for every protocol into ``directory`` (made if
    missing); returns the files written."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for protocol in PROTOCOLS:
        path = directory / f"plcstack_{protocol}.lua"
        path.write_text(lua_source(protocol), encoding="utf-8")
        written.append(path)
    return written
