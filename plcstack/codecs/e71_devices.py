"""MELSEC devices (spec §5): device table, CPU groups and their ranges, address parsing.

A device designation on the wire is the 48-bit field ``code << 32 | number`` (§3 rule 3).
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass
from typing import Final

from plcstack.codecs.e71_wire import Malformed, Reader
from plcstack.errors import AddressError, LocalProtocolError

__all__ = [
    "DEVICE_BY_CODE",
    "SPECIAL_FIRST",
    "SPECIAL_LAST",
    "WIDEST_RANGES",
    "CpuGroup",
    "Device",
    "DeviceRef",
    "check_ref",
    "decode_ref",
    "dev_value",
    "device_ranges",
    "in_range",
    "parse_address",
]


class Device(enum.Enum):
    """A device of §5.1: its wire code, whether it is a bit device, the base of its numbers."""

    X = ("X", 0x5820, True, 16)
    Y = ("Y", 0x5920, True, 16)
    M = ("M", 0x4D20, True, 10)
    F = ("F", 0x4620, True, 10)
    B = ("B", 0x4220, True, 16)
    TS = ("TS", 0x5453, True, 10)
    TC = ("TC", 0x5443, True, 10)
    TN = ("TN", 0x544E, False, 10)
    CS = ("CS", 0x4353, True, 10)
    CC = ("CC", 0x4343, True, 10)
    CN = ("CN", 0x434E, False, 10)
    D = ("D", 0x4420, False, 10)
    W = ("W", 0x5720, False, 16)
    R = ("R", 0x5220, False, 10)

    def __init__(self, letters: str, code: int, is_bit: bool, base: int) -> None:
        self.letters = letters
        self.code = code
        self.is_bit = is_bit
        self.base = base

    def format_number(self, number: int) -> str:
        return f"{self.letters}{number:X}" if self.base == 16 else f"{self.letters}{number}"


DEVICE_BY_CODE: Final[dict[int, Device]] = {d.code: d for d in Device}
#: L (latch relay) and S (step relay) share the M address space on the A series (§5.1, §13 A9)
_ALIASES: Final = {"L": Device.M, "S": Device.M}
_NAMES: Final[dict[str, Device]] = {d.letters: d for d in Device} | _ALIASES

#: special relays / registers M9000-M9255, D9000-D9255 exist in every CPU group (§5.2)
SPECIAL_FIRST: Final = 9000
SPECIAL_LAST: Final = 9255


class CpuGroup(enum.Enum):
    """CPU groups of §5.2 (device ranges differ). VII = A3A/A3U/A4U/Q3A/Q4A."""

    I = "I"  # noqa: E741 - the spec's own name
    II = "II"
    III = "III"
    IV = "IV"
    V = "V"
    VI = "VI"
    VII = "VII"


_XY_LAST = {
    "I": 0xFF,
    "II": 0x1FF,
    "III": 0x3FF,
    "IV": 0x7FF,
    "V": 0x1FF,
    "VI": 0x3FF,
    "VII": 0x7FF,
}
_R_LAST = {"I": -1, "II": 4095, "III": 4095, "IV": 8191, "V": 8191, "VI": 8191, "VII": 8191}


def device_ranges(group: CpuGroup) -> dict[Device, int]:
    """Highest device number per device for ``group`` (§5.2); -1 = device absent.

    M and D additionally have 9000-9255 (special relays/registers) in every group.
    """
    big = group.value in ("V", "VI", "VII")
    xy = _XY_LAST[group.value]
    timers = 2047 if big else 255
    counters = 1023 if big else 255
    return {
        Device.X: xy,
        Device.Y: xy,
        Device.M: 8191 if big else 2047,
        Device.F: 2047 if big else 255,
        Device.B: 0xFFF if big else 0x3FF,
        Device.TS: timers,
        Device.TC: timers,
        Device.TN: timers,
        Device.CS: counters,
        Device.CC: counters,
        Device.CN: counters,
        Device.D: 6143 if big else 1023,
        Device.W: 0xFFF if big else 0x3FF,
        Device.R: _R_LAST[group.value],
    }


#: the widest range of any group: what a client accepts without knowing the CPU
WIDEST_RANGES: Final[dict[Device, int]] = {
    d: max(device_ranges(g)[d] for g in CpuGroup) for d in Device
}


def in_range(device: Device, first: int, count: int, last: dict[Device, int]) -> bool:
    """Whether ``first .. first+count-1`` lies in one valid range of ``device``."""
    end = first + count - 1
    if first >= 0 and end <= last[device]:
        return True
    return device in (Device.M, Device.D) and first >= SPECIAL_FIRST and end <= SPECIAL_LAST


@dataclass(frozen=True, slots=True)
class DeviceRef:
    """One device point, e.g. ``DeviceRef(Device.D, 100)``; ``str()`` gives ``D100``."""

    device: Device
    number: int

    def __str__(self) -> str:
        return self.device.format_number(self.number)


def parse_address(text: str, *, last: dict[Device, int] | None = None) -> DeviceRef:
    """``D100``, ``X1F`` (hex), ``M8000``, ``TN5``, ``L100`` (= M100) -> :class:`DeviceRef`.

    Numbers beyond the widest CPU group of §5.2 (or ``last``) are an :class:`AddressError`.
    """
    if last is None and isinstance(text, str):
        return _parse_cached(text)
    return _parse(text, last)


@functools.lru_cache(maxsize=4096)
def _parse_cached(text: str) -> DeviceRef:
    # pollers ask for the same few addresses over and over; DeviceRef is immutable
    return _parse(text, None)


def _parse(text: str, last: dict[Device, int] | None) -> DeviceRef:
    if not isinstance(text, str):
        raise AddressError(f"address {text!r} is not a string")
    upper = text.strip().upper()
    device: Device | None = None
    digits = ""
    for size in (2, 1):
        if len(upper) > size and upper[:size] in _NAMES:
            device, digits = _NAMES[upper[:size]], upper[size:]
            break
    if device is None:
        known = ", ".join([*(d.letters for d in Device), "L", "S"])
        raise AddressError(f"unknown MELSEC device in address {text!r}; known: {known}")
    try:
        if not digits or not all(c in "0123456789ABCDEF" for c in digits):
            raise ValueError
        number = int(digits, device.base)
    except ValueError:
        kind = "hexadecimal" if device.base == 16 else "decimal"
        raise AddressError(
            f"address {text!r}: {device.letters} takes a {kind} device number"
        ) from None
    if not in_range(device, number, 1, last or WIDEST_RANGES):
        raise AddressError(f"address {text!r}: device number out of range for {device.letters}")
    return DeviceRef(device, number)


def dev_value(ref: DeviceRef) -> int:
    """The 48-bit wire field of a device designation (§3 rule 3)."""
    return ref.device.code << 32 | ref.number


def check_ref(ref: DeviceRef) -> None:
    """Our caller's device reference fits the field; :class:`LocalProtocolError` if not."""
    if (
        not isinstance(ref, DeviceRef)
        or not isinstance(ref.number, int)
        or not 0 <= ref.number <= 0xFFFFFFFF
    ):
        raise LocalProtocolError(f"not a device reference: {ref!r}")


def decode_ref(r: Reader) -> DeviceRef:
    """Read a device designation; an unknown device code is end code 56H."""
    value = r.num(6)
    dcode, number = value >> 32, value & 0xFFFFFFFF
    device = DEVICE_BY_CODE.get(dcode)
    if device is None:
        raise Malformed(0x56, f"unknown device code {dcode:04X}H")
    return DeviceRef(device, number)
