"""What the three S5 clients (S5-LAN-LINK, AS511, FETCH/WRITE) share above their wire: one naming
for DB, flag and I/O access, and the STEP 5 notation for a bit of a word or byte.

Every S5 client reads ``plc.read("DB10.DW5", 4)``; these methods give the same operations the
names a STEP 5 user looks for, with the same signatures on all three clients (AS511 has its own,
transaction-level implementations of the same names):

* ``read_db(db, dw, count)`` / ``write_db(db, dw, words)`` (``dx=True`` for DX blocks),
  ``read_dx`` / ``write_dx``;
* ``read_bytes(area, offset, count) -> bytes`` / ``write_bytes(area, offset, data)`` for flags
  (``M``), inputs (``I``/``E``) and outputs (``Q``/``A``).

Bits (:meth:`S5Access.split_bit`, used by ``read_as(address, BOOL)``): ``DB10.DW5.3`` or STEP 5's
``DB10.D5.3`` (bit 3 of DW5, bit 0 = least significant), ``M10.3`` / ``MB10.3`` (bit 3 of flag
byte 10), ``E0.1`` / ``I0.1``, ``A4.7`` / ``Q4.7``, ``MW10.12``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Final, Protocol

from plcstack.errors import AddressError
from plcstack.s5address import S5Area

__all__ = ["S5Access"]

_BIT: Final = re.compile(r"^(.*)\.(\d{1,2})$")
_DB_BIT_WORD: Final = re.compile(r"^(DB|DX)(\d+)\.D(\d+)$", re.IGNORECASE)
_AREA_BIT_BYTE: Final = re.compile(r"^([MEIAQ])(\d+)$", re.IGNORECASE)
_BYTE_AREAS: Final = {
    "M": "MB",
    "E": "EB",
    "I": "EB",
    "A": "AB",
    "Q": "AB",
    S5Area.FLAGS: "MB",
    S5Area.INPUTS: "EB",
    S5Area.OUTPUTS: "AB",
}


class _S5Points(Protocol):
    """The host client's point API the shared methods are built on."""

    name: str

    async def read(self, address: str, count: int = 1) -> list[int]: ...

    async def write(self, address: str, values: int | Sequence[int]) -> None: ...


def _byte_area(area: S5Area | str, name: str) -> str:
    key = area.upper() if isinstance(area, str) else area
    prefix = _BYTE_AREAS.get(key)
    if prefix is None:
        raise AddressError(
            f"read_bytes/write_bytes take M, I/E or Q/A, not {area!r}; DBs: read_db, "
            "timers and counters: read('T5', n)",
            plc=name,
        )
    return prefix


class S5Access:
    """Mixin of the S5 clients: DB/flag/IO access by the same names and the bit notation."""

    def split_bit(self, address: str) -> tuple[str, int | None]:
        """``(word or byte address, bit)`` of STEP 5 bit notation, else ``(address, None)``."""
        m = _BIT.match(address.strip())
        if m is None:
            return address, None
        head, bit = m.group(1), int(m.group(2))
        db = _DB_BIT_WORD.match(head)
        if db:
            head = f"{db.group(1).upper()}{db.group(2)}.DW{db.group(3)}"
        area = _AREA_BIT_BYTE.match(head)
        if area:
            head = f"{_BYTE_AREAS[area.group(1).upper()]}{area.group(2)}"
        return head, bit

    async def read_db(
        self: _S5Points, number: int, dw: int, count: int, *, dx: bool = False
    ) -> list[int]:
        """``count`` data words from DW ``dw`` of DB (or DX) ``number``."""
        return await self.read(f"{'DX' if dx else 'DB'}{number}.DW{dw}", count)

    async def write_db(
        self: _S5Points, number: int, dw: int, words: Sequence[int], *, dx: bool = False
    ) -> None:
        """Data words from DW ``dw`` of DB (or DX) ``number``; confirmed by the PLC."""
        await self.write(f"{'DX' if dx else 'DB'}{number}.DW{dw}", list(words))

    async def read_dx(self: _S5Points, number: int, dw: int, count: int) -> list[int]:
        return await self.read(f"DX{number}.DW{dw}", count)

    async def write_dx(self: _S5Points, number: int, dw: int, words: Sequence[int]) -> None:
        await self.write(f"DX{number}.DW{dw}", list(words))

    async def read_bytes(self: _S5Points, area: S5Area | str, offset: int, count: int) -> bytes:
        """``count`` bytes of flags (M), inputs (I/E) or outputs (Q/A) from byte ``offset``."""
        return bytes(await self.read(f"{_byte_area(area, self.name)}{offset}", count))

    async def write_bytes(self: _S5Points, area: S5Area | str, offset: int, data: bytes) -> None:
        await self.write(f"{_byte_area(area, self.name)}{offset}", list(data))
