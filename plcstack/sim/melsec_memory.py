"""The device memory and CPU state of a simulated MELSEC A-series PLC (spec §5.2, §1.2, §7.1).

Used by the E71 simulator and by PLC programs in tests and the demo::

    mem = MelsecMemory()                      # CPU group VII (A3A/A3U/A4U): the widest ranges
    mem.write_words("D", 100, [1, 2, 3])
    mem.read_bits("M", 0, 8)                  # -> [False] * 8
    mem.state = CpuState.STOP                 # remote STOP / key switch
    mem.write_in_run = False                  # DIP switch SW7 (SW3) OFF: no writes in RUN (55H)

Device names are the letter codes of §5.1 (``"X"``, ``"Y"``, ``"M"``, ``"L"``, ``"S"``, ``"F"``,
``"B"``, ``"TS"``, ``"TC"``, ``"TN"``, ``"CS"``, ``"CC"``, ``"CN"``, ``"D"``, ``"W"``, ``"R"``;
L and S are M). Word access to a bit device packs 16 points per word, bit 0 = the first point
(§6.2); bit access to a word device is refused (58H), as the E71 does.
"""

from __future__ import annotations

import enum
from array import array
from collections.abc import Iterable, Sequence

from plcstack.codecs.e71 import (
    SPECIAL_LAST,
    CpuGroup,
    Device,
    DeviceRef,
    device_ranges,
    in_range,
)

__all__ = ["CpuState", "MelsecAccessError", "MelsecMemory"]

_ALIASES = {"L": Device.M, "S": Device.M}


class CpuState(enum.Enum):
    RUN = "RUN"
    STOP = "STOP"
    PAUSE = "PAUSE"


class MelsecAccessError(ValueError):
    """An access the E71 would refuse; ``end_code`` is what it sends (56H, 57H, 58H)."""

    def __init__(self, end_code: int, message: str) -> None:
        super().__init__(message)
        self.end_code = end_code


def _device(device: str | Device) -> Device:
    if isinstance(device, Device):
        return device
    name = device.upper()
    if name in _ALIASES:
        return _ALIASES[name]
    try:
        return Device[name]
    except KeyError:
        raise MelsecAccessError(0x56, f"unknown device {device!r}") from None


class MelsecMemory:
    """Device memory of one CPU, its RUN/STOP/PAUSE state and the write-during-RUN switch.

    ``group`` selects the device ranges of §5.2 (default VII, the largest; R exists except in
    group I). Also holds the monitor registration, which lives in the CPU and is shared by all
    connections (§7.3, §13 A10).
    """

    def __init__(
        self,
        group: CpuGroup | str = CpuGroup.VII,
        *,
        state: CpuState = CpuState.RUN,
        write_in_run: bool = True,
    ) -> None:
        self.group = group if isinstance(group, CpuGroup) else CpuGroup(group)
        self.last = device_ranges(self.group)
        self.state = state
        self.write_in_run = write_in_run
        #: (06H -> "bits" | 07H -> "words", registered points) or None
        self.monitor: tuple[str, tuple[DeviceRef, ...]] | None = None
        self._bits: dict[Device, bytearray] = {}
        self._words: dict[Device, array[int]] = {}
        for dev in Device:
            size = max(self.last[dev], SPECIAL_LAST if dev in (Device.M, Device.D) else -1) + 1
            if dev.is_bit:
                self._bits[dev] = bytearray(size)
            else:
                self._words[dev] = array("H", bytes(2 * size))

    # -- checks -------------------------------------------------------------------------------
    def check(self, device: str | Device, start: int, count: int) -> Device:
        """Device of ``start .. start+count-1`` or :class:`MelsecAccessError` (58H head out of
        range / device absent, 57H span beyond the last device)."""
        dev = _device(device)
        if not in_range(dev, start, 1, self.last):
            raise MelsecAccessError(
                0x58, f"{dev.format_number(start) if start >= 0 else start}: head out of range"
            )
        if count < 1 or not in_range(dev, start, count, self.last):
            raise MelsecAccessError(
                0x57, f"{dev.format_number(start)} + {count} points exceeds the device range"
            )
        return dev

    @property
    def writes_allowed(self) -> bool:
        """Whether the E71 may write now (§7.1): in STOP always, in RUN/PAUSE only with the
        write-during-RUN switch on. [R] PAUSE is treated as RUN (the CPU is not stopped)."""
        return self.state is CpuState.STOP or self.write_in_run

    # -- the public API the demo's PLC program uses ----------------------------------------
    def read_bits(self, device: str | Device, start: int, count: int) -> list[bool]:
        dev = self.check(device, start, count)
        if not dev.is_bit:
            raise MelsecAccessError(0x58, f"{dev.letters} is a word device")
        cells = self._bits[dev]
        return [bool(b) for b in cells[start : start + count]]

    def write_bits(self, device: str | Device, start: int, values: Sequence[bool]) -> None:
        dev = self.check(device, start, len(values))
        if not dev.is_bit:
            raise MelsecAccessError(0x58, f"{dev.letters} is a word device")
        self._bits[dev][start : start + len(values)] = bytes(1 if v else 0 for v in values)

    def read_words(self, device: str | Device, start: int, count: int) -> list[int]:
        dev = _device(device)
        if dev.is_bit:
            self.check(dev, start, 16 * count)
            cells = self._bits[dev]
            out = []
            for w in range(count):
                base = start + 16 * w
                value = 0
                for i in range(16):
                    if cells[base + i]:
                        value |= 1 << i
                out.append(value)
            return out
        self.check(dev, start, count)
        return self._words[dev][start : start + count].tolist()

    def write_words(self, device: str | Device, start: int, values: Sequence[int]) -> None:
        dev = _device(device)
        for v in values:
            if not 0 <= v <= 0xFFFF:
                raise ValueError(f"word value {v} outside 0..65535")
        if dev.is_bit:
            self.check(dev, start, 16 * len(values))
            cells = self._bits[dev]
            for w, value in enumerate(values):
                base = start + 16 * w
                for i in range(16):
                    cells[base + i] = (value >> i) & 1
            return
        self.check(dev, start, len(values))
        self._words[dev][start : start + len(values)] = array("H", values)

    # -- helpers for random (test/monitor) access ----------------------------------------------
    def read_refs_bits(self, refs: Iterable[DeviceRef]) -> list[bool]:
        return [self.read_bits(r.device, r.number, 1)[0] for r in refs]

    def read_refs_words(self, refs: Iterable[DeviceRef]) -> list[int]:
        return [self.read_words(r.device, r.number, 1)[0] for r in refs]
