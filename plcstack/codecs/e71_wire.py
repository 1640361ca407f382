"""E71 wire helpers (spec §3): the field reader and writer every E71 codec module shares.

Everything on the wire is a sequence of little-endian numeric fields or byte strings (§3). ASCII
prints each numeric field of width w as 2w upper-case hex digits, most significant first, and each
byte as 2 hex digits; so one field list serves both codes and they cannot drift apart. Bit data
are the nibble-packed bytes of §6.1 (whose hex rendering is the one-character-per-point form).

The names here are public so the sibling modules (``e71_commands``, ``e71_buffers``,
``e71_programs``) and the simulator import them as a contract rather than reaching into privates.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Sequence
from typing import Final

from plcstack.errors import LocalProtocolError

__all__ = [
    "DEFAULT_PC",
    "DEFAULT_TIMER",
    "HEX",
    "HEX_UPPER",
    "Code",
    "Malformed",
    "Reader",
    "Writer",
    "as_code",
    "count_from",
    "pack_bits",
    "unpack_bits",
]

#: PC number of the CPU in the station where the E71 is mounted (§4.2)
DEFAULT_PC: Final = 0xFF
#: ACPU monitoring timer, units of 250 ms; 000AH = 2.5 s, the value most tools send (§4.2)
DEFAULT_TIMER: Final = 0x000A


class Code(enum.Enum):
    """Module-wide code selection (DIP switch SW2, §0): never detected from the data (§11.4)."""

    BINARY = "binary"
    ASCII = "ascii"


def as_code(code: Code | str) -> Code:
    """``Code`` from a ``Code`` or its value; anything else is our caller's misuse."""
    try:
        return code if isinstance(code, Code) else Code(code)
    except ValueError:
        raise LocalProtocolError(f"code must be 'binary' or 'ascii', not {code!r}") from None


HEX: Final = frozenset(b"0123456789ABCDEFabcdef")
HEX_UPPER: Final = frozenset(b"0123456789ABCDEF")


def pack_bits(values: Sequence[bool]) -> bytes:
    """§6.1: two points per byte, first point in the high nibble, odd count padded with 0."""
    out = bytearray((len(values) + 1) // 2)
    for i, v in enumerate(values):
        if v:
            out[i >> 1] |= 0x01 if i & 1 else 0x10
    return bytes(out)


def unpack_bits(data: bytes, count: int) -> tuple[bool, ...]:
    """Inverse of :func:`pack_bits`; only the nibble's least significant bit counts (§6.1)."""
    return tuple(bool(data[i >> 1] & (0x01 if i & 1 else 0x10)) for i in range(count))


class Writer:
    """Collects fields in wire order; renders binary (LE) or ASCII (hex, MSD first)."""

    __slots__ = ("ascii", "parts")

    def __init__(self, ascii_: bool) -> None:
        self.ascii = ascii_
        self.parts: list[bytes] = []

    def num(self, value: int, width: int) -> None:
        if self.ascii:
            self.parts.append(b"%0*X" % (2 * width, value))
        else:
            self.parts.append(value.to_bytes(width, "little"))

    def words(self, values: Sequence[int]) -> None:
        if self.ascii:
            self.parts.append(struct.pack(f">{len(values)}H", *values).hex().upper().encode())
        else:
            self.parts.append(struct.pack(f"<{len(values)}H", *values))

    def raw(self, data: bytes) -> None:
        self.parts.append(data.hex().upper().encode() if self.ascii else data)

    def getvalue(self) -> bytes:
        return b"".join(self.parts)


class Malformed(Exception):
    """The reader hit non-hex text (ASCII) or ran out of data: carries the E71's end code, so the
    E71 side answers with it and the partner side turns it into a RemoteProtocolError."""

    def __init__(self, end_code: int, reason: str) -> None:
        super().__init__(reason)
        self.end_code = end_code
        self.reason = reason
        self.pc: int | None = None


class Reader:
    """Reads fields from one complete frame (binary bytes or ASCII text)."""

    __slots__ = ("ascii", "data", "hexset", "pos")

    def __init__(self, data: bytes, ascii_: bool, *, lower_ok: bool = True) -> None:
        self.data = data
        self.ascii = ascii_
        self.pos = 0
        self.hexset = HEX if lower_ok else HEX_UPPER

    def _text(self, nchars: int) -> bytes:
        end = self.pos + nchars
        if end > len(self.data):
            raise Malformed(0x57, "message shorter than its fields")
        chunk = self.data[self.pos : end]
        if not self.hexset.issuperset(chunk):
            raise Malformed(0x54, f"non-hex characters {chunk!r}")
        self.pos = end
        return chunk

    def num(self, width: int) -> int:
        if self.ascii:
            return int(self._text(2 * width), 16)
        end = self.pos + width
        if end > len(self.data):
            raise Malformed(0x57, "message shorter than its fields")
        value = int.from_bytes(self.data[self.pos : end], "little")
        self.pos = end
        return value

    def raw(self, nbytes: int) -> bytes:
        if self.ascii:
            return bytes.fromhex(self._text(2 * nbytes).decode())
        end = self.pos + nbytes
        if end > len(self.data):
            raise Malformed(0x57, "message shorter than its fields")
        out = self.data[self.pos : end]
        self.pos = end
        return out

    def words(self, count: int) -> tuple[int, ...]:
        if self.ascii:
            text = self._text(4 * count)
            return struct.unpack(f">{count}H", bytes.fromhex(text.decode()))
        end = self.pos + 2 * count
        if end > len(self.data):
            raise Malformed(0x57, "message shorter than its fields")
        values = struct.unpack_from(f"<{count}H", self.data, self.pos)
        self.pos = end
        return values


def count_from(r: Reader) -> int:
    """The point-count field ``n, 00H`` (00H = 256); 57H when it is neither that nor 00H, 01H."""
    low = r.num(1)
    fixed = r.num(1)
    value = low | fixed << 8
    if value > 256:
        raise Malformed(0x57, f"point count field {value:#06x} is neither n,00 nor 00,01")
    return value or 256
