"""Which areas, data blocks and devices network clients may write through a face.

A face puts a PLC's memory on the network; a wrong write can move a machine. So nothing is
writable until configured, and the configuration names what may be written. An S5 PLC
(:class:`WriteAllowList`):

``DB10``, ``DB10-20``, ``DB*`` (every DB), the same with ``DX``; the areas ``M`` (flags),
``Q``/``A`` (outputs), ``I``/``E`` (input image), ``T`` (timers), ``C``/``Z`` (counters);
``AS`` (absolute memory, FETCH/WRITE ORG 'AS': anything, headers of blocks included); ``*``
(everything). Items are separated by commas or spaces, letters are case-insensitive.

A MELSEC PLC (:class:`DeviceAllowList`), in the same grammar: a device (``D``, ``M``, ``Y``,
``W``, ``B``, ``R``, ``TN``, ``CN``, ``TS``, ``TC``, ``CS``, ``CC``, ``X``, ``F``; ``L`` and ``S``
are ``M``), one point of it (``D100``) or a range (``D100-199`` or ``D100-D199``), numbers in
the device's own notation (hexadecimal for X, Y, B, W); ``*`` (every device).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Final

from plcstack.codecs.e71_devices import Device, DeviceRef, parse_address
from plcstack.errors import AddressError
from plcstack.sim.s5memory import Area, BlockType
from plcstack.sim.s5store import ABSOLUTE, Target

__all__ = ["DeviceAllowList", "WriteAllowList"]

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


@dataclass(frozen=True)
class DeviceAllowList:
    """Parsed MELSEC allow-list; ``allows(device, first, points)`` decides. Empty: nothing."""

    #: device -> inclusive point ranges (a whole device: one range over every number)
    ranges: dict[Device, tuple[tuple[int, int], ...]] = field(default_factory=dict)

    @classmethod
    def parse(cls, text: str) -> DeviceAllowList:
        """Read ``"D100-199, M, Y0-1F"``; a bad item is an :class:`AddressError` naming it."""
        ranges: dict[Device, list[tuple[int, int]]] = {}
        for item in re.split(r"[,\s]+", text.strip().upper()):
            if not item:
                continue
            if item == "*":
                for device in Device:
                    ranges.setdefault(device, []).append((0, 0xFFFFFFFF))
                continue
            whole = _device_named(item)
            if whole is not None:
                ranges.setdefault(whole, []).append((0, 0xFFFFFFFF))
                continue
            head, dash, tail = item.partition("-")
            try:
                first = last = parse_address(head)
                if dash:
                    letters = first.device.letters
                    # the end with or without the letters: D100-199, D100-D199, W10-W1F
                    number = tail[len(letters) :] if tail.startswith(letters) else tail
                    last = parse_address(letters + number)
            except AddressError as exc:
                raise AddressError(
                    f"writable: {item!r} is not a MELSEC device (D, M, Y, ...), a point (D100) "
                    f"or a range (D100-199): {exc.message}"
                ) from None
            if last.number < first.number:
                raise AddressError(f"writable: {item!r}: a range runs from low to high")
            ranges.setdefault(first.device, []).append((first.number, last.number))
        return cls({k: tuple(v) for k, v in ranges.items()})

    def allows(self, device: Device, first: int, points: int = 1) -> bool:
        """Whether every point ``first .. first + points - 1`` of ``device`` may be written."""
        last = first + points - 1
        return any(lo <= first and last <= hi for lo, hi in self.ranges.get(device, ()))

    def allows_ref(self, ref: DeviceRef, points: int = 1) -> bool:
        return self.allows(ref.device, ref.number, points)

    def __str__(self) -> str:
        parts = []
        for device, spans in self.ranges.items():
            for lo, hi in spans:
                if (lo, hi) == (0, 0xFFFFFFFF):
                    parts.append(device.letters)
                elif lo == hi:
                    parts.append(device.format_number(lo))
                else:
                    parts.append(f"{device.format_number(lo)}-{device.format_number(hi)}")
        return ", ".join(parts) or "nothing"


def _device_named(item: str) -> Device | None:
    """The device an item names as a whole (``D``, ``TN``, ``L`` = M), else None."""
    if item in ("L", "S"):
        return Device.M
    return next((d for d in Device if d.letters == item), None)
