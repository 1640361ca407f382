"""Delimited text as the engineering tools write it: encoding, delimiter, rows with line numbers.

The tools differ: Kepware writes comma- (or semicolon-) separated text in the Windows code page
or UTF-8; GX Developer writes comma-separated Shift-JIS; GX Works2 writes tab-separated UTF-16
with a byte-order mark. :func:`decode` picks the encoding from the bytes (a BOM, else strict
UTF-8, else the ``fallback`` code page) so the same reader takes every form, and :func:`rows`
keeps the file's line number of each record for the one-line error ``FILE:ROW: ...``.
"""

from __future__ import annotations

import codecs
import csv
import io
from collections.abc import Iterator
from dataclasses import dataclass

from plcstack.errors import AddressError

__all__ = ["Row", "TagListError", "decode", "rows", "sniff_delimiter"]

#: longest file taken: a tag list of 100,000 tags is a few MB; more is not a tag list
MAX_BYTES = 64 * 1024 * 1024


class TagListError(AddressError):
    """A tag list that cannot be converted: ``FILE:ROW: column 'C': why`` (or ``FILE: why`` for
    the file as a whole). An :class:`AddressError`, so the CLI exits 2 like any bad input."""

    @classmethod
    def at(cls, source: str, row: int | None, column: str | None, why: str) -> TagListError:
        where = f"{source}:{row}" if row is not None else source
        what = f"column {column!r}: " if column else ""
        return cls(f"{where}: {what}{why}")


@dataclass(frozen=True)
class Row:
    """One record: its cells (as written, spaces kept) and the line it starts on (1-based)."""

    line: int
    cells: tuple[str, ...]


def decode(data: bytes, source: str, *, fallback: str) -> str:
    """The text of ``data``: UTF-16/UTF-8 by their BOM, else UTF-8 if valid, else ``fallback``
    (``cp1252`` for Kepware, ``cp932`` = Shift-JIS for GX Developer)."""
    if len(data) > MAX_BYTES:
        raise TagListError.at(source, None, None, f"larger than {MAX_BYTES} bytes")
    for bom, encoding in (
        (codecs.BOM_UTF8, "utf-8-sig"),
        (codecs.BOM_UTF16_LE, "utf-16"),
        (codecs.BOM_UTF16_BE, "utf-16"),
    ):
        if data.startswith(bom):
            try:
                return data.decode(encoding)
            except UnicodeDecodeError as exc:
                raise TagListError.at(
                    source, None, None, f"not valid {encoding} text (byte {exc.start})"
                ) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        pass
    try:
        return data.decode(fallback)
    except UnicodeDecodeError as exc:
        raise TagListError.at(
            source, None, None, f"neither UTF-8 nor {fallback} text (byte {exc.start})"
        ) from None


def sniff_delimiter(text: str, choices: str) -> str:
    """The one of ``choices`` seen most in the first non-blank line (the heading record);
    ``choices[0]`` when none is seen."""
    first = next((line for line in text.splitlines() if line.strip()), "")
    counts = {c: first.count(c) for c in choices}
    best = max(choices, key=lambda c: counts[c])
    return best if counts[best] else choices[0]


def rows(text: str, source: str, delimiter: str) -> Iterator[Row]:
    """The records of ``text`` with their first line numbers; blank records are skipped."""
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter, strict=True)
    start = 1
    try:
        for cells in reader:
            line, start = start, reader.line_num + 1
            if any(c.strip() for c in cells):
                yield Row(line, tuple(cells))
    except csv.Error as exc:
        raise TagListError.at(source, reader.line_num, None, f"not valid CSV: {exc}") from None
