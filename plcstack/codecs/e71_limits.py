"""Per-request limits of the E71 (spec §7.1, §7.3), shared by the client and the simulator.

The client checks them before sending (a :class:`~plcstack.errors.LocalProtocolError`); the
simulator answers the same cases with the end codes 57H / 58H of §10. The checks work on any
request that names its command, device points and count (:class:`Counted`), so this module needs
only the device table, not the request classes.
"""

from __future__ import annotations

from typing import ClassVar, Final, Protocol

from plcstack.codecs.e71_devices import SPECIAL_FIRST, Device, DeviceRef

__all__ = [
    "BIT_UNIT_COMMANDS",
    "Counted",
    "command_limit",
    "head_ok",
    "limit_error",
    "unit_error",
]

#: commands that work in bit units (the others in word units)
BIT_UNIT_COMMANDS: Final = frozenset({0x00, 0x02, 0x04, 0x06})


class Counted(Protocol):
    """What the limit checks read of a request (00H-09H)."""

    COMMAND: ClassVar[int]

    def device_refs(self) -> tuple[DeviceRef, ...]:
        """The device points named on the wire (heads of batches, test and monitor points)."""
        ...

    def point_count(self) -> int:
        """The value of the point-count field (0 for 08H/09H)."""
        ...


def command_limit(command: int, device: Device | None) -> int:
    """Most points per request (§7.1). Word-unit commands on bit devices count words.

    For 05H/07H with a mix of devices the smaller (entry) limit applies: 40 / 20 entries.
    [R] decision (§7.1 footnote): the "X counts twice" rule for non-AnA CPUs is not applied;
    the client cannot know the CPU and the simulator defaults to an AnA group (VII). A count
    field of 00H means 256 and is refused with 57H where the limit is lower (§13 A5).
    """
    if device is not None and device.is_bit:
        return _LIMITS_BIT[command]
    return _LIMITS_WORD[command]


_LIMITS_WORD: Final = {0x00: 256, 0x01: 256, 0x02: 256, 0x03: 256, 0x04: 80, 0x05: 40, 0x06: 40}
_LIMITS_WORD[0x07] = 20
_LIMITS_BIT: Final = {**_LIMITS_WORD, 0x01: 128, 0x03: 40}


def head_ok(ref: DeviceRef) -> bool:
    """A word-unit command may name a bit device only at a head that is a multiple of 16."""
    if not ref.device.is_bit:
        return True
    base = SPECIAL_FIRST if ref.device is Device.M and ref.number >= SPECIAL_FIRST else 0
    return (ref.number - base) % 16 == 0


def unit_error(req: Counted) -> str | None:
    """End code 58H cases that need no CPU knowledge: word device in a bit-unit command, bit
    device head not a multiple of 16 in a word-unit command (§7.3, §10.1)."""
    bit_unit = req.COMMAND in BIT_UNIT_COMMANDS
    for ref in req.device_refs():
        if bit_unit and not ref.device.is_bit:
            return f"{ref} is a word device; command {req.COMMAND:02X}H works in bit units"
        if not bit_unit and not head_ok(ref):
            return f"{ref}: a bit device in word units needs a head that is a multiple of 16"
    return None


def limit_error(req: Counted) -> str | None:
    """End code 57H for a count outside 1..limit of §7.1, else ``None``."""
    if req.COMMAND in (0x08, 0x09):
        return None  # monitors carry no count: they read what 06H/07H registered
    n = req.point_count()
    refs = req.device_refs()
    device = refs[0].device if len(refs) == 1 or req.COMMAND < 0x04 else None
    limit = command_limit(req.COMMAND, device)
    if not isinstance(n, int) or not 1 <= n <= limit:
        unit = (
            "words" if device is not None and device.is_bit and req.COMMAND in (1, 3) else "points"
        )
        return f"command {req.COMMAND:02X}H takes 1-{limit} {unit}, got {n}"
    return None
