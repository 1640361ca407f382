"""How a tag's values sit in Modbus registers and bits: one :class:`Layout` per mapped tag.

The Modbus face serves each value in the plain form a panel expects of a Modbus device, whatever
the PLC family stores (BCD, S5 KG, KT ...): the value the poller decoded, encoded again:

================================================  =======================  ========================
tag type                                          registers per value      register contents
================================================  =======================  ========================
``bool``, a bit point (``raw`` over M, X, Y)      co/di: 1 bit; hr/ir: 1   0 or 1
8-, 16-bit integers, ``raw`` words and bytes,     1                        the number, two's
``kf``, ``kh``, ``km``, ``kz``, ``bcd16``                                  complement (``bcd16``
                                                                           1234 is 1234)
``int32``, ``uint32``, ``bcd32``                  2, in ``word_order``     the number, two's
                                                                           complement
``float32``, ``kg``, ``kt`` (seconds), any tag    2, in ``word_order``     IEEE 754 float32
with ``scale``
``string:N``, ``kc``                              ceil(N / 2)              2 Latin-1 characters,
                                                                           first in the high
                                                                           byte, NUL-padded
``ky``                                            1                        high byte, low byte
================================================  =======================  ========================

A scaled tag serves its engineering value as a float32 pair (what the poller delivers; the raw
number is not served), and a write of one is scaled back by the poller. ``count > 1`` puts the
values one after another. ``word_order = "big"`` (the default) sends the high word first.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

from plcstack.poll.config import TagConfig
from plcstack.values import WordOrder

__all__ = ["BIT_TABLES", "TABLES", "Layout", "layout_for"]

#: the four Modbus data tables, by the name the config uses
TABLES = ("co", "di", "hr", "ir")
#: tables of single bits (coils, discrete inputs); the others hold 16-bit registers
BIT_TABLES = ("co", "di")

_F32 = struct.Struct(">f")
_U32 = struct.Struct(">I")


class EncodeError(ValueError):
    """A value that has no register form (a KG real beyond float32's range)."""


@dataclass(frozen=True, slots=True)
class Layout:
    """Where one tag sits: ``table``, first address ``start``, ``width`` registers (or bits) per
    value, ``count`` values; ``kind`` says how a value becomes registers."""

    table: str
    start: int
    width: int
    count: int
    #: "bit", "int16", "uint16", "int32", "uint32", "float32", "text", "bytes"
    kind: str

    @property
    def size(self) -> int:
        return self.width * self.count

    @property
    def end(self) -> int:
        """One past the last address."""
        return self.start + self.size

    def encode(self, value: Any, order: WordOrder) -> list[int]:
        """The tag's registers (or bits as 0/1) for a sample's value; raises EncodeError."""
        items = value if self.count > 1 else [value]
        if not isinstance(items, list | tuple) or len(items) != self.count:
            raise EncodeError(f"expected {self.count} values, got {value!r}")
        out: list[int] = []
        for item in items:
            out.extend(self._encode_one(item, order))
        return out

    def _encode_one(self, value: Any, order: WordOrder) -> list[int]:
        kind = self.kind
        if kind == "bit":
            return [1 if value else 0]
        if kind in ("int16", "uint16"):
            return [int(value) & 0xFFFF]
        if kind in ("int32", "uint32"):
            return _pair(int(value) & 0xFFFFFFFF, order)
        if kind == "float32":
            number = float(value)
            if math.isfinite(number) and abs(number) > 3.4028234663852886e38:
                raise EncodeError(f"{number!r} is beyond float32's range")
            (bits,) = _U32.unpack(_F32.pack(number))
            return _pair(bits, order)
        if kind == "bytes":
            high, low = value
            return [(int(high) & 0xFF) << 8 | (int(low) & 0xFF)]
        # text: two characters per register, NUL-padded to the layout's width
        raw = str(value).encode("latin-1", "replace").ljust(2 * self.width, b"\0")
        return [raw[i] << 8 | raw[i + 1] for i in range(0, 2 * self.width, 2)]

    def decode(self, words: list[int], order: WordOrder) -> Any:
        """The value to write for the tag's registers (the inverse of :meth:`encode`)."""
        values = [
            self._decode_one(words[i : i + self.width], order)
            for i in range(0, len(words), self.width)
        ]
        return values if self.count > 1 else values[0]

    def _decode_one(self, words: list[int], order: WordOrder) -> Any:
        kind = self.kind
        if kind == "bit":
            return bool(words[0])
        if kind == "uint16":
            return words[0]
        if kind == "int16":
            return words[0] - 0x10000 if words[0] & 0x8000 else words[0]
        if kind in ("int32", "uint32", "float32"):
            high, low = (words[0], words[1]) if order is WordOrder.BIG else (words[1], words[0])
            bits = high << 16 | low
            if kind == "float32":
                return _F32.unpack(_U32.pack(bits))[0]
            if kind == "int32" and bits & 0x80000000:
                return bits - 0x100000000
            return bits
        if kind == "bytes":
            return (words[0] >> 8, words[0] & 0xFF)
        raw = b"".join(w.to_bytes(2, "big") for w in words)
        return raw.split(b"\0", 1)[0].decode("latin-1")


def _pair(bits: int, order: WordOrder) -> list[int]:
    high, low = bits >> 16, bits & 0xFFFF
    return [high, low] if order is WordOrder.BIG else [low, high]


def layout_for(tag: TagConfig, point_bits: int, table: str, start: int) -> Layout:
    """The layout of ``tag`` at ``table:start``; ValueError saying why it cannot sit there.

    ``point_bits`` is the width of the tag's points in the PLC (1 for bit areas, 8 or 16), which
    decides what a ``raw`` tag is.
    """
    vtype = tag.type
    bit = vtype.kind == "bool" or (vtype.kind == "raw" and point_bits == 1)
    if table in BIT_TABLES:
        if not bit:
            raise ValueError(
                f"a {'coil' if table == 'co' else 'discrete input'} holds one bit; "
                f"type {vtype.name} needs hr or ir"
            )
        return _checked(Layout(table, start, 1, tag.count, "bit"))
    if bit:
        kind, width = "bit", 1
    elif tag.scale is not None or vtype.kind == "float":
        kind, width = "float32", 2
    elif vtype.kind == "text":
        kind, width = "text", -(-vtype.bits // 16)
    elif vtype.kind == "bytes":
        kind, width = "bytes", 1
    else:  # integers of every width, BCD, raw words and bytes
        bits = vtype.bits or point_bits
        signed = vtype.signed
        if bits <= 16:
            kind, width = ("int16" if signed else "uint16"), 1
        else:
            kind, width = ("int32" if signed else "uint32"), 2
    return _checked(Layout(table, start, width, tag.count, kind))


def _checked(layout: Layout) -> Layout:
    if layout.end > 0x10000:
        raise ValueError(
            f"{layout.size} {'bits' if layout.kind == 'bit' else 'registers'} from "
            f"{layout.start} run past the last address 65535"
        )
    return layout
