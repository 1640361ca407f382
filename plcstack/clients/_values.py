"""Fast paths for the value lists of writes (issue 8 follow-up).

A 64-word write spent more time validating and packing its values one by one in Python than the
rest of the request took together. These functions make the same checks with C-level builtins
(``set(map(type, ...))``, ``struct``, ``min``/``max``) and return ``None`` whenever a value is not
a plain ``int`` in range, so that the caller's per-value loop still runs and words its precise
error (which value, why). They accept nothing the slow paths refuse: ``bool``, ``int`` subclasses
and anything else that is not exactly ``int`` always take the slow path.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Final, Literal

__all__ = ["pack_ints", "plain_words"]

_INT: Final = frozenset({int})


def _all_plain_ints(values: object) -> bool:
    return (
        (type(values) is list or type(values) is tuple)
        and len(values) > 0
        and set(map(type, values)) == _INT
    )


def pack_ints(
    values: Sequence[int], order: Literal["<", ">"], code: Literal["H", "B"]
) -> bytes | None:
    """``values`` packed as unsigned ``code`` items (``H`` word, ``B`` byte) in byte ``order``,
    when every value is a plain ``int`` in -32768..65535 (words) or -128..255 (bytes); negatives
    are sent as two's complement. ``None`` otherwise."""
    if not _all_plain_ints(values):
        return None
    fmt = f"{order}{len(values)}{code}"
    try:
        return struct.pack(fmt, *values)  # struct checks the unsigned range itself
    except struct.error:
        pass
    bits = 16 if code == "H" else 8
    if min(values) < -(1 << (bits - 1)) or max(values) >= 1 << bits:
        return None
    mask = (1 << bits) - 1
    return struct.pack(fmt, *[v & mask for v in values])


def plain_words(values: Sequence[int]) -> tuple[int, ...] | None:
    """``values`` as unsigned 16-bit words when all are plain ints in -32768..65535, else None."""
    if not _all_plain_ints(values):
        return None
    low, high = min(values), max(values)
    if low >= 0 and high <= 0xFFFF:
        return tuple(values)
    if low >= -0x8000 and high <= 0xFFFF:
        return tuple([v & 0xFFFF for v in values])
    return None
