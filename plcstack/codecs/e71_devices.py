"""MELSEC devices (spec §5): device table, CPU groups and their ranges, address parsing.

A device designation on the wire is the 48-bit field ``code << 32 | number`` (§3 rule 3).
"""

from __future__ import annotations

import enum
import functools
import re
from dataclasses import dataclass
from typing import Final

from plcstack.codecs.e71_wire import Malformed, Reader
from plcstack.errors import AddressError, LocalProtocolError
from plcstack.s5address import READ_A_BIT, parse_s5_address

__all__ = [
    "DEVICE_BY_CODE",
    "DEVICE_NAMES",
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
    "foreign_notation",
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
#: the name of each device (§5.1 "Name"), as the Wireshark dissector shows it
DEVICE_NAMES: Final[dict[Device, str]] = {
    Device.X: "input",
    Device.Y: "output",
    Device.M: "internal, latch or step relay",
    Device.F: "annunciator",
    Device.B: "link relay",
    Device.TS: "timer contact",
    Device.TC: "timer coil",
    Device.TN: "timer current value",
    Device.CS: "counter contact",
    Device.CC: "counter coil",
    Device.CN: "counter current value",
    Device.D: "data register",
    Device.W: "link register",
    Device.R: "file register",
}
#: L (latch relay) and S (step relay) share the M address space on the A series (§5.1, §13 A9)
_ALIASES: Final = {"L": Device.M, "S": Device.M}
_NAMES: Final[dict[str, Device]] = {d.letters: d for d in Device} | _ALIASES

#: special relays / registers M9000-M9255, D9000-D9255 exist in every CPU group (§5.2)
SPECIAL_FIRST: Final = 9000
SPECIAL_LAST: Final = 9255

#: devices of the later MELSEC series (Q, L, iQ-R; GX Works projects and device comments name
#: them) that the 1E frame of an A-series E71 does not address (§5.1): what each is, and what
#: the A series has instead where it has something
_OTHER_SERIES: Final[dict[str, str]] = {
    "SM": "a special relay of the Q/L and iQ-R series; the A series has special relays"
    f" M{SPECIAL_FIRST}-M{SPECIAL_LAST} instead (e.g. SM400 'always ON' is M9036)",
    "SD": "a special register of the Q/L and iQ-R series; the A series has special registers"
    f" D{SPECIAL_FIRST}-D{SPECIAL_LAST} instead",
    "SB": "a link special relay of the Q/L series, which the 1E frame does not reach",
    "SW": "a link special register of the Q/L series, which the 1E frame does not reach",
    "ZR": "a file register of the Q/L series in serial numbering; the 1E frame reaches the"
    " A series' file registers as R",
    "DX": "a direct input of the Q/L series; the 1E frame reads inputs as X",
    "DY": "a direct output of the Q/L series; the 1E frame reads outputs as Y",
    "LB": "a link relay of the iQ-R series; the 1E frame reaches link relays as B",
    "LW": "a link register of the iQ-R series; the 1E frame reaches link registers as W",
    "RD": "a refresh data register of the iQ-R series, which the 1E frame does not reach",
    "Z": "an index register, which the 1E frame does not reach",
    "V": "an index register (or edge relay), which the 1E frame does not reach",
    "U": "a module's buffer memory (U\\G), which the 1E frame reaches by its own commands",
}


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
    other = _other_series(upper)
    if other and not _foreign(upper):  # DX3.DW0 is an S5 data block, not a direct input
        raise AddressError(f"address {text!r}: {other}")
    device: Device | None = None
    digits = ""
    for size in (2, 1):
        if len(upper) > size and upper[:size] in _NAMES:
            device, digits = _NAMES[upper[:size]], upper[size:]
            break
    if device is None:
        foreign = _foreign(upper)
        if foreign:
            raise AddressError(f"address {text!r}{foreign}")
        known = ", ".join([*(d.letters for d in Device), "L", "S"])
        raise AddressError(f"unknown MELSEC device in address {text!r}; known: {known}")
    try:
        if not digits or not all(c in "0123456789ABCDEF" for c in digits):
            raise ValueError
        number = int(digits, device.base)
        if device.base == 10 and not digits.isdigit():
            raise ValueError
    except ValueError:
        raise AddressError(_bad_number(text, upper, device, digits)) from None
    ranges = last or WIDEST_RANGES
    if not in_range(device, number, 1, ranges):
        raise AddressError(
            f"address {text!r}: device number out of range for {device.letters}"
            f" ({_range_text(device, ranges)})"
        )
    return DeviceRef(device, number)


def _other_series(upper: str) -> str:
    """What a device of another MELSEC series is (``_OTHER_SERIES``), or "" when ``upper``
    is none: a letter pair of those series followed by a number (``SM400``), where the A
    series' parser would take the first letter for a device of its own (``S`` = ``M``) and
    complain about the rest ("'M400' is not one")."""
    for size in (2, 1):
        what = _OTHER_SERIES.get(upper[:size])
        rest = upper[size:]
        if what and rest and rest[0].isdigit():
            return f"{upper[:size]} is {what}"
    return ""


def _range_text(device: Device, last: dict[Device, int]) -> str:
    """``D0-D6143, D9000-D9255``: the numbers ``device`` takes, in its own notation, so a
    refused address shows the valid ones instead of sending the user to a table."""
    letters, width = device.letters, "X" if device.base == 16 else "d"
    if last[device] < 0:
        return f"this CPU has no {letters}"
    text = f"{letters}0-{letters}{last[device]:{width}}"
    if device in (Device.M, Device.D):
        text += f", {letters}{SPECIAL_FIRST}-{letters}{SPECIAL_LAST}"
    return text


#: what a digit typed as a letter usually was (``D1O0``, ``DI00``)
_LOOKALIKES: Final = str.maketrans({"O": "0", "I": "1", "L": "1"})
#: the hexadecimal devices, for the message of a decimal one given hex digits
_HEX_NAMES: Final = ", ".join(d.letters for d in Device if d.base == 16)


def foreign_notation(text: str) -> str:
    """``": that is Siemens S5 notation ..."`` when ``text`` is an address of the S5 family,
    else ``""``: what a MELSEC address parser or bit-of-a-word check adds to its message, so
    ``DB10.DW0`` gets the same words from ``plcstack read``, the Python API and a TOML tag."""
    return _foreign(text.strip().upper())


def _foreign(upper: str) -> str:
    """`` (... notation; ...)`` when ``upper`` is an address of the Siemens S5 family (``DB10.DW0``,
    ``MB100``, ``M10.3``), else ``""``: the message then says what the PLC family expects
    instead of complaining about the digits of a device it never meant."""
    try:
        s5 = parse_s5_address(upper)
    except AddressError:
        if not _S5_SHAPE.fullmatch(upper):
            return ""
        return (
            ": that is Siemens S5/S7 notation, but this is a MELSEC PLC; use device letters "
            "and numbers like D100 (data register), M0 (relay), X1F (input, hex)"
        )
    return (
        f": that is Siemens S5 notation ({s5}), but this is a MELSEC PLC; use device letters "
        "and numbers like D100 (data register), M0 (relay), X1F (input, hex)"
    )


#: S5/S7 operand shapes the S5 parser refuses but still recognises as its own family
_S5_SHAPE: Final = re.compile(r"(DB|DX)\d+\..*|[MEIAQ][BWD]?\d+\.\d+|[MEIAQ][BWD]\d+")


def _bad_number(text: str, upper: str, device: Device, digits: str) -> str:
    """The message for a device letter followed by something that is not its number."""
    foreign = _foreign(upper)
    if foreign:
        return f"address {text!r}{foreign}"
    word, dot, bit = digits.partition(".")
    if dot and word and bit and not device.is_bit:
        return (
            f"address {text!r} is a bit of the word {device.letters}{word}: {READ_A_BIT}; "
            "a plain read or write takes whole points"
        )
    kind = "hexadecimal (0-9, A-F)" if device.base == 16 else "decimal"
    example = device.format_number(0x1F if device.base == 16 else 100)
    message = f"address {text!r}: {device.letters} takes a {kind} device number like {example}"
    fixed = digits.translate(_LOOKALIKES)
    allowed = "0123456789ABCDEF" if device.base == 16 else "0123456789"
    if fixed != digits and fixed and all(c in allowed for c in fixed):
        return f"{message}; did you mean {device.letters}{fixed}?"
    if device.base == 10 and digits and all(c in "0123456789ABCDEF" for c in digits):
        return f"{message}, not hexadecimal {digits!r} (hexadecimal devices: {_HEX_NAMES})"
    return f"{message}; {digits!r} is not one" if digits else f"{message}; the number is missing"


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
