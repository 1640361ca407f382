"""S5 operand notation, shared by the three S5 protocols (S5-LAN-LINK, AS511, FETCH/WRITE).

``parse_s5_address("DB10.DW5")`` gives an :class:`S5Address`; every protocol then maps it onto
its own wire fields (S5-LAN area letter and start, FETCH/WRITE ORG id, AS511 absolute address).

Accepted notation (case-insensitive, German and English mnemonics)::

    DB10.DW5  DX3.DW0     data word 5 of DB10 / DW0 of DX3         WORD, offset = DW number
    DB10.DL5  DB10.DR5    left (high) / right (low) byte of DW5    BYTE, offset = 10 / 11
    DB10.DBB3             byte 3 of the DB body (= DB10.DR1)       BYTE, offset = 3
    MB100  MW10           flag byte 100 / flag word 10 = MB10+MB11 offset = byte number
    IB0 EB0  IW0 EW0      inputs (process image), byte / word      offset = byte number
    QB0 AB0  QW0 AW0      outputs (process image), byte / word     offset = byte number
    T5                    timer word 5                             WORD, offset = 5
    C5 Z5                 counter word 5                           WORD, offset = 5

Decisions where S5 usage is not uniform:

* ``DB10.DBW10`` is S7 notation, where 10 is a *byte* offset (it would be DW5 here). Accepting it
  would let one string mean DW5 to one reader and DW10 to another, so it is refused with a
  message naming the S5 equivalent. ``DB10.DBB3`` has no such ambiguity and is accepted.
* ``MW10`` is the word whose high byte is MB10 (S5 operand convention), so MW10 and MW11 overlap.
* Bit operands (``M10.3``, ``E0.0``, ``DB10.DW5.3``) are not points: none of the three
  protocols transfers a single bit. A typed read takes them as ``BOOL`` (``--type bool``,
  ``read_as("M10.3", BOOL)``: the byte or word is read and the bit picked); a plain read or any
  write of one is refused with that advice. Double words (``MD``, ``DD``) are refused: read two
  words (or a 32-bit type).
* Numbers: DB/DX 1..255 (DB0 is the block address list, not a data block), offsets 0..65535;
  each protocol checks its own narrower limits.
"""

from __future__ import annotations

import enum
import functools
import re
from dataclasses import dataclass
from typing import Final

from plcstack.errors import AddressError

__all__ = [
    "FETCHWRITE_ORG",
    "S5Address",
    "S5Area",
    "S5Unit",
    "parse_s5_address",
]


class S5Area(enum.Enum):
    """The memory areas an S5 operand can name. Values are the German STEP 5 letters."""

    DB = "DB"
    DX = "DX"
    FLAGS = "M"
    INPUTS = "E"
    OUTPUTS = "A"
    TIMERS = "T"
    COUNTERS = "Z"

    @property
    def is_block(self) -> bool:
        """``True`` for DB and DX, whose addresses carry a block number."""
        return self in (S5Area.DB, S5Area.DX)

    @property
    def letter_en(self) -> str:
        """English mnemonic letter (I, Q, C) where it differs from the German one."""
        return {"E": "I", "A": "Q", "Z": "C"}.get(self.value, self.value)


class S5Unit(enum.Enum):
    BYTE = 1
    WORD = 2

    @property
    def size(self) -> int:
        """Bytes per point."""
        return self.value


#: FETCH/WRITE ORG ids (spec C.6.3) for each area, for the FETCH/WRITE codec and client
FETCHWRITE_ORG: Final[dict[S5Area, int]] = {
    S5Area.DB: 0x01,
    S5Area.FLAGS: 0x02,
    S5Area.INPUTS: 0x03,
    S5Area.OUTPUTS: 0x04,
    S5Area.COUNTERS: 0x06,
    S5Area.TIMERS: 0x07,
    S5Area.DX: 0x0A,
}

MAX_OFFSET: Final = 0xFFFF


@dataclass(frozen=True, slots=True)
class S5Address:
    """One S5 operand: area, unit, block number (DB/DX only) and offset.

    ``offset`` means:

    * DB/DX, WORD: the data word number n of ``DWn``;
    * DB/DX, BYTE: the byte number in the block body (``DLn`` = 2n, ``DRn`` = 2n + 1);
    * M/E/A, BYTE and WORD: the byte number (``MW10`` starts at MB10);
    * T/Z: the timer / counter number (always WORD).

    Point ``k`` of a multi-point access is :meth:`shifted` by ``k``: the next word of a DB, the
    next byte for bytes, the *next word* (offset + 2) for M/E/A words, the next timer/counter.
    """

    area: S5Area
    unit: S5Unit
    offset: int
    db: int | None = None

    def __post_init__(self) -> None:
        if self.area.is_block:
            if self.db is None or not 1 <= self.db <= 255:
                raise AddressError(f"{self.area.value} number {self.db} is outside 1..255")
        elif self.db is not None:
            raise AddressError(f"area {self.area.value} takes no block number")
        if self.area in (S5Area.TIMERS, S5Area.COUNTERS) and self.unit is not S5Unit.WORD:
            raise AddressError(f"{self.area.value} is word-only")
        if not 0 <= self.offset <= MAX_OFFSET:
            raise AddressError(f"offset {self.offset} is outside 0..{MAX_OFFSET}")

    # -- geometry --------------------------------------------------------------------------
    @property
    def step(self) -> int:
        """How far ``offset`` moves per point (2 for M/E/A words, else 1)."""
        if self.unit is S5Unit.WORD and self.area in (
            S5Area.FLAGS,
            S5Area.INPUTS,
            S5Area.OUTPUTS,
        ):
            return 2
        return 1

    @property
    def byte_offset(self) -> int:
        """Byte offset from the start of the area or of the block body (DW0)."""
        if self.unit is S5Unit.WORD and self.step == 1:
            return 2 * self.offset  # DW n, T n, Z n: one word each
        return self.offset

    def byte_length(self, count: int) -> int:
        """Number of data bytes ``count`` points cover."""
        return count * self.unit.size

    def shifted(self, points: int) -> S5Address:
        """The address ``points`` points further on (same area, unit and block)."""
        return S5Address(self.area, self.unit, self.offset + points * self.step, self.db)

    # -- text ------------------------------------------------------------------------------
    def to_str(self, english: bool = False) -> str:
        """Canonical notation: German letters (``EB0``, ``Z5``) unless ``english``."""
        letter = self.area.letter_en if english else self.area.value
        if self.area.is_block:
            if self.unit is S5Unit.WORD:
                return f"{letter}{self.db}.DW{self.offset}"
            half = "DR" if self.offset % 2 else "DL"
            return f"{letter}{self.db}.{half}{self.offset // 2}"
        if self.area in (S5Area.TIMERS, S5Area.COUNTERS):
            return f"{letter}{self.offset}"
        return f"{letter}{'W' if self.unit is S5Unit.WORD else 'B'}{self.offset}"

    def __str__(self) -> str:
        return self.to_str()


_BLOCK_RE = re.compile(r"(DB|DX)(\d{1,5})\.(DW|DL|DR|DBB|DBW|DBD|DBX|DD|D)(\d{1,5})(\.\d+)?")
_AREA_RE = re.compile(r"(M|E|I|A|Q)(B|W|D)?(\d{1,5})(\.\d+)?")
_TC_RE = re.compile(r"(T|C|Z)(\d{1,5})")

_AREA_LETTERS: Final = {
    "M": S5Area.FLAGS,
    "E": S5Area.INPUTS,
    "I": S5Area.INPUTS,
    "A": S5Area.OUTPUTS,
    "Q": S5Area.OUTPUTS,
}

#: the one advice for a bit operand, whichever family's parser meets it
READ_A_BIT: Final = "read it as a bool (--type bool, or read_as(address, BOOL) in Python)"

_HELP = (
    "expected S5 notation such as DB10.DW5, DX3.DW0, DB10.DL5, MB100, MW10, IB0/EB0, "
    "QW0/AW0, T5, C5/Z5"
)


def parse_s5_address(text: str) -> S5Address:
    """Parse S5 operand notation (see the module docstring); :class:`AddressError` otherwise."""
    if isinstance(text, str):
        return _parse_cached(text)
    raise AddressError(f"address {text!r} is not a string; {_HELP}")


@functools.lru_cache(maxsize=4096)
def _parse_cached(text: str) -> S5Address:
    # Pollers ask for the same few addresses over and over, and S5Address is immutable; errors
    # are not cached (lru_cache does not keep exceptions), so every bad address is re-checked.
    norm = text.strip().upper()
    try:
        return _parse(norm, text)
    except AddressError as exc:
        if exc.message.startswith(repr(text)):
            raise
        raise AddressError(f"{text!r}: {exc.message}") from None


def _parse(norm: str, text: str) -> S5Address:
    m = _BLOCK_RE.fullmatch(norm)
    if m:
        kind, number, op, index, bit = m.groups()
        area = S5Area.DB if kind == "DB" else S5Area.DX
        db, n = int(number), int(index)
        if db == 0:
            raise AddressError(f"{kind}0 is not a data block (it holds the block address list)")
        if bit or op in ("DBX", "D"):
            return _bit_operand(f"{kind}{db}.DW{n}" if op in ("DW", "D") else None)
        if op in ("DBD", "DD"):
            raise AddressError("double words are not supported; read two data words")
        if op == "DBW":
            hint = (
                f"use {kind}{db}.DW{n // 2} (bytes {n}..{n + 1})"
                if n % 2 == 0
                else f"S5 data words start at even bytes; byte {n} is {kind}{db}.DR{n // 2}"
            )
            raise AddressError(
                f"{kind}{db}.DBW{n} is S7 notation (byte offset) and ambiguous in S5; {hint}"
            )
        if op == "DW":
            return S5Address(area, S5Unit.WORD, n, db)
        if op == "DBB":
            return S5Address(area, S5Unit.BYTE, n, db)
        return S5Address(area, S5Unit.BYTE, 2 * n + (1 if op == "DR" else 0), db)
    m = _AREA_RE.fullmatch(norm)
    if m:
        letter, size, index, bit = m.groups()
        if bit is not None or size is None:
            return _bit_operand(f"{letter}{size or 'B'}{index}")
        if size == "D":
            raise AddressError(f"double words are not supported; read two words ({letter}W...)")
        unit = S5Unit.WORD if size == "W" else S5Unit.BYTE
        return S5Address(_AREA_LETTERS[letter], unit, int(index))
    m = _TC_RE.fullmatch(norm)
    if m:
        letter, index = m.groups()
        area = S5Area.TIMERS if letter == "T" else S5Area.COUNTERS
        return S5Address(area, S5Unit.WORD, int(index))
    melsec = _MELSEC.fullmatch(norm)
    if melsec:
        raise AddressError(
            f"{text!r} is not an S5 address but MELSEC notation (this is a Siemens S5 PLC); {_HELP}"
        )
    raise AddressError(f"{text!r} is not an S5 address; {_HELP}")


#: MELSEC device addresses (D100, X1F, TN5, W1A) that are no S5 operand
_MELSEC: Final = re.compile(r"(D|W|R|X|Y|B|F|L|S|TN|TS|TC|CN|CS|CC)[0-9A-F]+")


def _bit_operand(whole: str | None) -> S5Address:
    """A bit operand is not a point: the advice to read it as a bool (see the module doc)."""
    points = f"the {'word' if whole and 'W' in whole else 'byte'} {whole}" if whole else "points"
    raise AddressError(
        f"a bit operand is not a point: {READ_A_BIT}; a plain read or write takes {points}"
    )
