"""The history's on-disk encodings: a block of one tag's points, and a journal segment.

A **block** holds the points of one tag between two checkpoints, column by column, each column
in the narrowest fixed width that holds it, so decoding is C work (``array.frombytes`` and
``itertools.accumulate``) and not a Python loop per point:

* times: milliseconds since the block's first point, as differences to the previous point:
  ``uint16`` when every step is under 65.5 s (a tag polled every second: 2 bytes a point),
  else ``int32`` or ``int64`` (a clock set back makes a step negative; the block then says it
  is not in order and the reader sorts it);
* values: booleans one byte each; integers as differences to the previous value in 1, 2, 4 or 8
  bytes (a counter that moves by less than 128 a step: 1 byte); floats as ``float32`` when every
  value is one exactly (a PLC's REAL), else ``float64``; anything else (text, arrays, a mix of
  types, integers beyond 64 bits) as one JSON list;
* qualities: the indexes of the bad points (usually none), whose value slots hold a filler.

A **segment** is what the writer journals each second: every point it took in that second, for
every tag, as parallel columns (series id, time, kind, value); it lets a restart after a crash
rebuild the blocks that were not yet written. Segments are deleted at each checkpoint.

Both functions here are pure: bytes in, values out; malformed bytes raise :class:`BlockError`.
"""

from __future__ import annotations

import itertools
import json
import math
import struct
from array import array
from collections.abc import Sequence
from typing import Any

__all__ = [
    "BAD",
    "BOOL",
    "FLOAT",
    "INT",
    "OTHER",
    "BlockError",
    "OpenBlock",
    "decode_block",
    "decode_segment",
    "encode_block",
    "encode_segment",
    "kind_of",
]

#: the kind of each point while a block is open (one byte each)
BAD, BOOL, INT, FLOAT, OTHER = 0, 1, 2, 3, 4
#: integers up to this magnitude are held exactly in a float64 column while a block is open
_EXACT = 1 << 53

_VERSION = 1
_HEAD = struct.Struct("<BBBxII")  # version, time code, value code, pad, points, bad points
#: version, column codes (series, times, numbers), points, base time (ms), JSON bytes
_SEG_HEAD = struct.Struct("<BBBBIqI")
_FIRST = struct.Struct("<q")

#: time columns: array type codes by code byte
_TIME_CODES = {1: "H", 2: "i", 3: "q"}
#: value columns
_V_BOOL, _V_JSON = 1, 2
_V_INT = {3: "b", 4: "h", 5: "i", 6: "q"}
_V_FLOAT = {7: "f", 8: "d"}
_INT_LIMITS = ((3, 1 << 7), (4, 1 << 15), (5, 1 << 31), (6, 1 << 63))
_SORTED = 0x80  # in the time code byte: the times are in order


class BlockError(ValueError):
    """Bytes that are not a block or segment of this format (a damaged file)."""


def kind_of(value: Any) -> tuple[int, float]:
    """A good value's kind and its number in the open block's float column."""
    t = type(value)
    if t is float:
        return FLOAT, value
    if t is bool:
        return BOOL, 1.0 if value else 0.0
    if t is int and -_EXACT <= value <= _EXACT:
        return INT, float(value)
    return OTHER, 0.0


class OpenBlock:
    """One tag's points since the last checkpoint, in memory: times (ms), kinds, numbers, and
    the values that are not numbers by index."""

    __slots__ = ("kinds", "numbers", "others", "sid", "times")

    def __init__(self, sid: int) -> None:
        self.sid = sid
        self.times = array("q")
        self.numbers = array("d")
        self.kinds = bytearray()
        self.others: dict[int, Any] = {}

    def __len__(self) -> int:
        return len(self.times)

    def add(self, t_ms: int, kind: int, number: float, value: Any) -> None:
        if kind == OTHER:
            self.others[len(self.times)] = value
        elif kind == BAD and self.numbers:
            number = self.numbers[-1]  # the filler of a bad point: no jump in the column
        self.times.append(t_ms)
        self.numbers.append(number)
        self.kinds.append(kind)

    def clear(self) -> None:
        """Start afresh (after a checkpoint wrote the points)."""
        self.times = array("q")
        self.numbers = array("d")
        self.kinds = bytearray()
        self.others = {}

    def copy(self) -> OpenBlock:
        other = OpenBlock(self.sid)
        other.times = array("q", self.times)
        other.numbers = array("d", self.numbers)
        other.kinds = bytearray(self.kinds)
        other.others = dict(self.others)
        return other

    def points(self) -> tuple[list[int], list[Any]]:
        """``(times, values)`` in time order (a clock set back leaves them out of order)."""
        times, values = self.times.tolist(), self.values()
        if any(b < a for a, b in itertools.pairwise(times)):
            order = sorted(range(len(times)), key=times.__getitem__)
            times, values = [times[i] for i in order], [values[i] for i in order]
        return times, values

    def values(self) -> list[Any]:
        """The points' values (None where bad)."""
        out: list[Any] = []
        for i, (kind, number) in enumerate(zip(self.kinds, self.numbers, strict=True)):
            if kind == FLOAT:
                out.append(number)
            elif kind == INT:
                out.append(int(number))
            elif kind == BOOL:
                out.append(number != 0.0)
            elif kind == OTHER:
                out.append(self.others[i])
            else:
                out.append(None)
        return out


def _narrowest(deltas: Sequence[int], limits: tuple[tuple[int, int], ...]) -> int | None:
    lo, hi = (min(deltas), max(deltas)) if deltas else (0, 0)
    for code, limit in limits:
        if -limit <= lo and hi < limit:
            return code
    return None


def _diffs(values: Sequence[int]) -> list[int]:
    return [b - a for a, b in itertools.pairwise(values)]


def encode_block(block: OpenBlock) -> tuple[int, int, bytes]:
    """``(first ms, last ms, bytes)`` of an open block's points (it must hold one at least);
    first and last are the earliest and latest times, whatever their order."""
    times, kinds, numbers = block.times, bytes(block.kinds), block.numbers
    n = len(times)
    if n == 0:
        raise ValueError("an empty block is not written")
    steps = _diffs(times)
    in_order = not steps or min(steps) >= 0
    if in_order and (not steps or max(steps) < 65536):
        time_code = 1
    else:
        time_code = 2 if _narrowest(steps, ((2, 1 << 31),)) else 3
    time_column = array(_TIME_CODES[time_code], steps).tobytes()
    bad = array("I", (i for i, k in enumerate(kinds) if k == BAD)) if BAD in kinds else array("I")
    good = set(kinds) - {BAD}
    value_code, value_column = _encode_values(block, kinds, numbers, good)
    head = _HEAD.pack(_VERSION, time_code | (_SORTED if in_order else 0), value_code, n, len(bad))
    first, last = (times[0], times[-1]) if in_order else (min(times), max(times))
    return first, last, head + _FIRST.pack(times[0]) + time_column + value_column + bad.tobytes()


def _encode_values(
    block: OpenBlock, kinds: bytes, numbers: array[float], good: set[int]
) -> tuple[int, bytes]:
    if good <= {BOOL}:
        return _V_BOOL, bytes(map(bool, numbers))
    if good == {INT}:
        ints = list(map(int, numbers))
        steps = _diffs(ints)
        code = _narrowest(steps, _INT_LIMITS)
        if code is not None:
            return code, _FIRST.pack(ints[0]) + array(_V_INT[code], steps).tobytes()
    elif good == {FLOAT}:
        narrow = array("f", numbers)
        wide = array("d", narrow)
        # bit for bit (NaN != NaN would say no to every NaN): a REAL's values all fit
        if wide.tobytes() == numbers.tobytes():
            return 7, narrow.tobytes()
        return 8, numbers.tobytes()
    text = json.dumps(_json_values(block.values()), separators=(",", ":"), allow_nan=False)
    return _V_JSON, text.encode()


def _json_values(values: list[Any]) -> list[Any]:
    """Values for JSON: a non-finite float as ``{"f": "nan"}`` (JSON has none), so it comes
    back as the float it was and not as text."""
    out: list[Any] = []
    for v in values:
        if type(v) is float and not math.isfinite(v):
            out.append({"f": repr(v)})
        elif isinstance(v, list):
            out.append(_json_values(v))
        else:
            out.append(v)
    return out


def _from_json(values: list[Any]) -> list[Any]:
    out: list[Any] = []
    for v in values:
        if isinstance(v, dict):
            out.append(float(v["f"]))
        elif isinstance(v, list):
            out.append(_from_json(v))
        else:
            out.append(v)
    return out


def decode_block(t0: int, data: bytes) -> tuple[list[int], list[Any]]:
    """``(times in ms, values)`` of a block, in time order; a bad point's value is None.
    ``t0`` is the block's first time as its row stores it (checked against the bytes)."""
    try:
        version, time_code, value_code, n, n_bad = _HEAD.unpack_from(data)
        if version != _VERSION:
            raise BlockError(f"block format {version}, this version reads {_VERSION}")
        in_order = bool(time_code & _SORTED)
        offset = _HEAD.size
        (first,) = _FIRST.unpack_from(data, offset)
        offset += _FIRST.size
        steps = array(_TIME_CODES[time_code & ~_SORTED])
        size = steps.itemsize * (n - 1)
        steps.frombytes(data[offset : offset + size])
        offset += size
        times = list(itertools.accumulate(steps, initial=first))
        values, offset = _decode_values(value_code, data, offset, n, n_bad)
        bad = array("I")
        bad.frombytes(data[offset : offset + 4 * n_bad])
        offset += 4 * n_bad
    except (struct.error, KeyError, ValueError, UnicodeDecodeError, TypeError) as exc:
        if isinstance(exc, BlockError):
            raise
        raise BlockError(f"a damaged block: {exc}") from None
    if offset != len(data) or len(times) != n or len(values) != n or len(bad) != n_bad:
        raise BlockError(f"a damaged block: {len(data)} bytes for {n} points")
    if first < t0:
        raise BlockError("a damaged block: its first time is before its row's")
    for i in bad:
        if i >= n:
            raise BlockError("a damaged block: a bad point beyond its end")
        values[i] = None
    if not in_order:
        order = sorted(range(n), key=times.__getitem__)
        times = [times[i] for i in order]
        values = [values[i] for i in order]
    return times, values


def _decode_values(
    code: int, data: bytes, offset: int, n: int, n_bad: int
) -> tuple[list[Any], int]:
    if code == _V_BOOL:
        return list(map(bool, data[offset : offset + n])), offset + n
    if code in _V_INT:
        (first,) = _FIRST.unpack_from(data, offset)
        offset += _FIRST.size
        steps = array(_V_INT[code])
        size = steps.itemsize * (n - 1)
        steps.frombytes(data[offset : offset + size])
        return list(itertools.accumulate(steps, initial=first)), offset + size
    if code in _V_FLOAT:
        column = array(_V_FLOAT[code])
        size = column.itemsize * n
        column.frombytes(data[offset : offset + size])
        return column.tolist(), offset + size
    if code == _V_JSON:
        # the JSON is what is left but the bad indexes
        end = len(data) - 4 * n_bad
        values = json.loads(data[offset:end])
        if not isinstance(values, list):
            raise BlockError("a damaged block: its values are not a list")
        return _from_json(values), end
    raise BlockError(f"a damaged block: value code {code}")


def encode_segment(
    sids: array[int], times: array[int], kinds: bytearray, numbers: array[float], others: list[Any]
) -> bytes:
    """One second's points of every tag, as the journal keeps them until the next checkpoint:
    each column in the narrowest width that holds it (series ids in 2 bytes below 65,536,
    times as milliseconds from the first in 4, numbers as float32 when all of them are one: a
    second of 16-bit words or REALs costs 11 bytes a point)."""
    n = len(sids)
    base = times[0] if n else 0
    text = json.dumps(_json_values(others), separators=(",", ":"), allow_nan=False).encode()
    offsets = [t - base for t in times]
    sid_code = "H" if not n or max(sids) < 65536 else "I"
    fits = not n or (min(offsets) >= -(1 << 31) and max(offsets) < (1 << 31))
    offset_code = "i" if fits else "q"
    narrow = array("f", numbers)
    number_code = "f" if array("d", narrow).tobytes() == numbers.tobytes() else "d"
    return (
        _SEG_HEAD.pack(
            _VERSION, ord(sid_code), ord(offset_code), ord(number_code), n, base, len(text)
        )
        + array(sid_code, sids).tobytes()
        + array(offset_code, offsets).tobytes()
        + bytes(kinds)
        + (narrow if number_code == "f" else numbers).tobytes()
        + text
    )


def decode_segment(data: bytes) -> list[tuple[int, int, int, float, Any]]:
    """``(sid, ms, kind, number, value)`` of each point of a segment (value: for OTHER)."""
    try:
        version, sid_code, offset_code, number_code, n, base, text_size = _SEG_HEAD.unpack_from(
            data
        )
        if version != _VERSION:
            raise BlockError(f"journal format {version}, this version reads {_VERSION}")
        codes = chr(sid_code), chr(offset_code), chr(number_code)
        if codes[0] not in "HI" or codes[1] not in "iq" or codes[2] not in "fd":
            raise BlockError(f"a damaged journal segment: column codes {codes}")
        offset = _SEG_HEAD.size
        columns = []
        for code in codes[:2]:
            column = array(code)
            size = column.itemsize * n
            column.frombytes(data[offset : offset + size])
            columns.append(column)
            offset += size
        sids, offsets = columns
        kinds = data[offset : offset + n]
        offset += n
        numbers = array(codes[2])
        numbers.frombytes(data[offset : offset + numbers.itemsize * n])
        offset += numbers.itemsize * n
        others = _from_json(json.loads(data[offset : offset + text_size]))
        offset += text_size
    except (struct.error, ValueError, UnicodeDecodeError, TypeError, KeyError) as exc:
        if isinstance(exc, BlockError):
            raise
        raise BlockError(f"a damaged journal segment: {exc}") from None
    if (
        offset != len(data)
        or len(kinds) != n
        or len(sids) != n
        or len(offsets) != n
        or len(numbers) != n
        or not isinstance(others, list)
    ):
        raise BlockError(f"a damaged journal segment: {len(data)} bytes for {n} points")
    rest = iter(others)
    points: list[tuple[int, int, int, float, Any]] = []
    for sid, off, kind, number in zip(sids, offsets, kinds, numbers, strict=True):
        value = next(rest, None) if kind == OTHER else None
        points.append((sid, base + off, kind, number, value))
    return points
