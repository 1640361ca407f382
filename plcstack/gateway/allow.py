"""Which areas and data blocks network clients may write through the gateway.

A gateway puts a PLC's memory on the network; a wrong write can move a machine. So nothing is
writable until configured, and the configuration names what may be written:

``DB10``, ``DB10-20``, ``DB*`` (every DB), the same with ``DX``; the areas ``M`` (flags),
``Q``/``A`` (outputs), ``I``/``E`` (input image), ``T`` (timers), ``C``/``Z`` (counters);
``AS`` (absolute memory, FETCH/WRITE ORG 'AS': anything, headers of blocks included); ``*``
(everything). Items are separated by commas or spaces, letters are case-insensitive.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Final

from plcstack.errors import AddressError
from plcstack.sim.s5memory import Area, BlockType
from plcstack.sim.s5store import ABSOLUTE, Target

__all__ = ["WriteAllowList"]

_AREA_NAMES: Final[dict[str, Area]] = {
    "M": Area.FLAGS,
    "Q": Area.OUTPUTS,
    "A": Area.OUTPUTS,
    "I": Area.INPUTS,
    "E": Area.INPUTS,
    "T": Area.TIMERS,
    "C": Area.COUNTERS,
    "Z": Area.COUNTERS,
}
_BLOCK = re.compile(r"(DB|DX)(\*|(\d+)(?:-(\d+))?)")


@dataclass(frozen=True)
class WriteAllowList:
    """Parsed allow-list; ``allows(target)`` decides. The empty list allows nothing."""

    areas: frozenset[Area] = frozenset()
    #: block type -> inclusive number ranges
    blocks: dict[BlockType, tuple[tuple[int, int], ...]] = field(default_factory=dict)
    absolute: bool = False

    @classmethod
    def parse(cls, text: str) -> WriteAllowList:
        """Read ``"DB10-20, M, Q"``; a bad item is an :class:`AddressError` naming it."""
        areas: set[Area] = set()
        blocks: dict[BlockType, list[tuple[int, int]]] = {}
        absolute = False
        for item in re.split(r"[,\s]+", text.strip().upper()):
            if not item:
                continue
            if item == "*":
                areas.update(_AREA_NAMES.values())
                for btype in (BlockType.DB, BlockType.DX):
                    blocks.setdefault(btype, []).append((1, 255))
                absolute = True
            elif item == "AS":
                absolute = True
            elif item in _AREA_NAMES:
                areas.add(_AREA_NAMES[item])
            elif m := _BLOCK.fullmatch(item):
                btype = BlockType.DB if m[1] == "DB" else BlockType.DX
                if m[2] == "*":
                    low, high = 1, 255
                else:
                    low = int(m[3])
                    high = int(m[4]) if m[4] else low
                if not 1 <= low <= high <= 255:
                    raise AddressError(f"writable: {item!r}: block numbers are 1..255, low to high")
                blocks.setdefault(btype, []).append((low, high))
            else:
                raise AddressError(
                    f"writable: {item!r} is not DBn, DBn-m, DB*, DXn..., M, Q/A, I/E, T, C/Z, "
                    "AS or *"
                )
        return cls(frozenset(areas), {k: tuple(v) for k, v in blocks.items()}, absolute=absolute)

    def allows(self, target: Target) -> bool:
        if isinstance(target, tuple):
            btype, number = target
            return any(lo <= number <= hi for lo, hi in self.blocks.get(btype, ()))
        if isinstance(target, Area):
            return target in self.areas
        return target == ABSOLUTE and self.absolute

    def __str__(self) -> str:
        parts = [a.value for a in sorted(self.areas, key=lambda a: a.value)]
        for btype, ranges in self.blocks.items():
            parts += [f"{btype.name}{lo}" + (f"-{hi}" if hi != lo else "") for lo, hi in ranges]
        if self.absolute:
            parts.append("AS")
        return ", ".join(parts) or "nothing"
