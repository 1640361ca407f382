"""Addresses in the notation of Kepware's drivers, turned into plcstack's.

plcstack's own notation (``D100``, ``X1F``, ``D120.3``, ``DB10.DW5``, ``MW10``) is taken as is.
On top of it, the forms Kepware's drivers print for the same locations:

- Mitsubishi (MELSEC): zero-padded device numbers (``D0100``, ``X001F``) -> ``D100``, ``X1F``;
  a bit of a word in two decimal digits (``D0120.03``, ``D0120.15``) -> plcstack's one
  hexadecimal digit (``D120.3``, ``D120.F``); one digit is taken as plcstack's (hexadecimal);
- Siemens S5: ``DB10:DW5``, ``DB10:DL5``, ``DB10:DR5``, ``DB10:DW5.3`` (colon between block and
  word) -> ``DB10.DW5`` ...; STEP 5's English flag mnemonics ``FY10`` / ``FW10`` -> ``MB10`` /
  ``MW10``;
- arrays of either family: ``D0100 [16]`` / ``D100[16]`` -> address ``D100`` with count 16;
- strings (Data Type ``String``): ``D100.20`` = 20 characters from ``D100`` (``H``/``L`` after
  the length, high or low byte first, must match the family's order: S5 ``H``, MELSEC ``L``).

The result is then checked by the PLC family's own address rules (:mod:`.convert`).
"""

from __future__ import annotations

import re

from plcstack.url import parse_url

__all__ = ["family", "native_address", "split_array", "split_string_length"]

_MELSEC = re.compile(r"^(TS|TC|TN|CS|CC|CN|[XYMFBDWRLS])([0-9A-F]+)(?:\.([0-9A-F]|\d\d))?$")
_S5_BLOCK = re.compile(r"^(DB|DX)0*(\d+)[:.](DW|DL|DR)0*(\d+)(?:\.0*(\d+))?$")
_S5_FLAG = re.compile(r"^F([YW])0*(\d+)$")
_ARRAY = re.compile(r"^(.*?)\s*\[\s*(\d+)\s*\]$")
_STRING = re.compile(r"^(.*)\.0*(\d+)([HL]?)$")


def family(url: str) -> str:
    """``melsec`` or ``s5``: whose address notation a PLC URL takes."""
    return "melsec" if parse_url(url).scheme.startswith("e71") else "s5"


def native_address(text: str, family: str) -> str:
    """plcstack's notation of ``text`` (unchanged when no Kepware form matches)."""
    upper = "".join(text.split()).upper()
    if family == "melsec":
        m = _MELSEC.match(upper)
        if m:
            number = m.group(2).lstrip("0") or "0"
            bit = m.group(3) or ""
            if len(bit) == 2:
                bit = f"{int(bit):X}" if int(bit) < 16 else bit
            bit = f".{bit}" if bit else ""
            return f"{m.group(1)}{number}{bit}"
        return text.strip()
    m = _S5_BLOCK.match(upper)
    if m:
        block, number, kind, word, bit = m.groups()
        return f"{block}{int(number)}.{kind}{int(word)}" + (f".{int(bit)}" if bit else "")
    m = _S5_FLAG.match(upper)
    if m:
        return f"M{'B' if m.group(1) == 'Y' else 'W'}{int(m.group(2))}"
    return text.strip()


def split_array(text: str) -> tuple[str, int | None]:
    """``("D100", 16)`` for ``D100 [16]``; ``(text, None)`` without brackets."""
    m = _ARRAY.match(text.strip())
    if not m:
        return text, None
    return m.group(1), int(m.group(2))


def split_string_length(text: str) -> tuple[str, int, str] | None:
    """``("D100", 20, "L")`` for ``D100.20L``; None when no length is given."""
    m = _STRING.match("".join(text.split()).upper())
    if not m:
        return None
    return m.group(1), int(m.group(2)), m.group(3)
