"""EXPERIMENTAL typed helpers for the E71 program/parameter/comment commands (spec §7.8).

The 1E layout of 0AH-0DH, 10H, 11H, 1CH-21H, 39H and 3AH is not documented anywhere public
(the seed's figures are lost, §13 A11). The codec therefore carries them as
:class:`~plcstack.codecs.e71_commands.OpaqueCommand` (command + raw body). The functions here build
and parse those bodies by the *reconstructed* layout of §7.8 — a decision [R], unverified against a
real E71: address (3 bytes for 10H/11H, else 2) · count (1 byte, 00H = 256) · 00H · data, where data
and answers are words for 0AH-0DH (steps / T,C set values) and bytes for everything else.
Use them only against the plcstack simulator or after checking a capture of real hardware.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from plcstack.codecs.e71_commands import OpaqueCommand, OpaqueResponse
from plcstack.codecs.e71_wire import (
    DEFAULT_PC,
    DEFAULT_TIMER,
    Code,
    Malformed,
    Reader,
    Writer,
    count_from,
)
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "PROGRAM_COMMANDS",
    "READS",
    "WORD_COMMANDS",
    "ProgramAccess",
    "build",
    "parse_request",
    "parse_response",
]

#: command -> (what, is_write) for the commands of §7.8 that carry address + count (12H has none)
PROGRAM_COMMANDS: Final[dict[int, tuple[str, bool]]] = {
    0x0A: ("main sequence program / T,C set values", False),
    0x0B: ("sub sequence program / T,C set values", False),
    0x0C: ("main sequence program / T,C set values", True),
    0x0D: ("sub sequence program / T,C set values", True),
    0x10: ("parameters", False),
    0x11: ("parameters", True),
    0x1C: ("comments", False),
    0x1D: ("comments", True),
    0x1E: ("microcomputer program MAIN", False),
    0x1F: ("microcomputer program SUB", False),
    0x20: ("microcomputer program MAIN", True),
    0x21: ("microcomputer program SUB", True),
    0x39: ("extended comments", False),
    0x3A: ("extended comments", True),
}
#: the word-unit commands (program steps / set values); the rest move bytes
WORD_COMMANDS: Final = frozenset({0x0A, 0x0B, 0x0C, 0x0D})
#: read command -> its write command
READS: Final = {0x0A: 0x0C, 0x0B: 0x0D, 0x10: 0x11, 0x1C: 0x1D, 0x1E: 0x20, 0x1F: 0x21, 0x39: 0x3A}


def _address_width(command: int) -> int:
    return 3 if command in (0x10, 0x11) else 2


@dataclass(frozen=True, slots=True)
class ProgramAccess:
    """One decoded [R] access: ``data`` is words (0AH-0DH) or bytes as ints, ``None`` for reads."""

    command: int
    address: int
    count: int
    data: tuple[int, ...] | None = None


def build(
    command: int,
    address: int,
    count_or_data: int | Sequence[int] | bytes,
    code: Code,
    *,
    pc: int = DEFAULT_PC,
    timer: int = DEFAULT_TIMER,
) -> OpaqueCommand:
    """An :class:`OpaqueCommand` for a read (``count``) or write (data) by the [R] layout."""
    if command not in PROGRAM_COMMANDS:
        raise LocalProtocolError(f"command {command!r} is not a program/parameter/comment command")
    is_write = PROGRAM_COMMANDS[command][1]
    width = _address_width(command)
    if not (isinstance(address, int) and 0 <= address < 1 << (8 * width)):
        raise LocalProtocolError(f"address {address!r} does not fit {width} bytes")
    w = Writer(code is Code.ASCII)
    words = command in WORD_COMMANDS
    if is_write:
        if isinstance(count_or_data, int):
            raise LocalProtocolError(f"command {command:02X}H writes: give the data")
        data = tuple(count_or_data)
        count = len(data)
        limit = 0xFFFF if words else 0xFF
        if any(not isinstance(v, int) or not 0 <= v <= limit for v in data):
            raise LocalProtocolError(f"data values must be 0..{limit}")
    else:
        if not isinstance(count_or_data, int):
            raise LocalProtocolError(f"command {command:02X}H reads: give the count")
        count, data = count_or_data, ()
    if not 1 <= count <= 256:
        raise LocalProtocolError(f"command {command:02X}H takes 1-256 per request, got {count}")
    w.num(address, width)
    w.num(count & 0xFF, 1)
    w.num(0, 1)
    if words:
        w.words(data)
    else:
        w.raw(bytes(data))
    answer = 0 if is_write else (2 * count if words else count)
    return OpaqueCommand(command, w.getvalue(), response_length=answer, pc=pc, timer=timer)


def parse_request(req: OpaqueCommand, code: Code) -> ProgramAccess:
    """Decode the body of ``req`` by the [R] layout; raises ``Malformed`` (57H / 54H)."""
    command = req.command
    if command not in PROGRAM_COMMANDS:
        raise Malformed(0x50, f"command {command:02X}H has no address/count body")
    r = Reader(req.body, code is Code.ASCII)
    address = r.num(_address_width(command))
    count = count_from(r)
    data: tuple[int, ...] | None = None
    if PROGRAM_COMMANDS[command][1]:
        data = r.words(count) if command in WORD_COMMANDS else tuple(r.raw(count))
    if r.pos != len(r.data):
        raise Malformed(0x57, "data count does not match")
    return ProgramAccess(command, address, count, data)


def parse_response(req: OpaqueCommand, resp: OpaqueResponse, code: Code) -> tuple[int, ...]:
    """Words (0AH/0BH) or bytes of a read's :class:`OpaqueResponse` by the [R] layout."""
    r = Reader(resp.data, code is Code.ASCII)
    try:
        if req.command in WORD_COMMANDS:
            return tuple(r.words(req.response_length // 2))
        return tuple(r.raw(req.response_length))
    except Malformed as exc:
        raise RemoteProtocolError(f"malformed {req.command | 0x80:02X}H data: {exc}") from None


def encode_answer(command: int, values: Sequence[int], code: Code) -> OpaqueResponse:
    """E71 side: the answer data of a read by the [R] layout."""
    w = Writer(code is Code.ASCII)
    if command in WORD_COMMANDS:
        w.words(values)
    else:
        w.raw(bytes(values))
    return OpaqueResponse(command, w.getvalue())
