"""Read plans: the fewest requests that cover a scan group's tags, and splitting replies back.

The protocols here pay one round trip per request, and a PLC's communication module answers
requests in sequence, so for a scan of 50 tags the number of frames is what costs. A plan sorts the
tags of one PLC by ``(area, index)`` from the client's :meth:`~plcstack.clients.base.Client.locate`
and merges a tag into the current request when the unused points between them are at most
``max_gap`` and the merged span still fits ``max_points(area)`` (the protocol's per-frame limit).
A tag longer than one frame is split over several requests and put back together.

A client without the merge hooks (they raise ``NotImplementedError``) is read tag by tag.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Hashable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from plcstack.clients.base import Client
from plcstack.errors import AddressError, PlcError, RemoteProtocolError
from plcstack.poll.config import TagConfig
from plcstack.values import (
    BOOL,
    RAW,
    ByteOrder,
    Endian,
    Point,
    Scalar,
    Scale,
    TagValue,
    ValueType,
    WordOrder,
    bits_of_points,
)

__all__ = [
    "Piece",
    "ReadRequest",
    "ScanPlan",
    "TagPlan",
    "TagResult",
    "build_plan",
    "describe",
    "encode_tag",
    "point_bits",
    "split_bit",
]

#: the point width a client without a ``point_bits(area)`` hook is assumed to have (words)
DEFAULT_POINT_BITS = 16


@dataclass(frozen=True, slots=True)
class ReadRequest:
    """One ``client.read(address, count)``; ``area``/``start`` are None when not mergeable."""

    address: str
    count: int
    area: Hashable | None = None
    start: int = 0


@dataclass(frozen=True, slots=True)
class Piece:
    """``length`` points of a tag found at ``offset`` within the reply to request ``request``."""

    request: int
    offset: int
    length: int


@dataclass(frozen=True, slots=True)
class TagPlan:
    tag: TagConfig
    pieces: tuple[Piece, ...]
    point_bits: int
    #: the bit within the first point for a bit-of-a-word tag (``D100.3``), else None
    bit: int | None = None
    #: order of the characters in a word (text types): the client's family
    byte_order: ByteOrder = Endian.BIG
    #: the requests this tag needs, ascending (precomputed: the poller reads it every scan)
    request_ids: tuple[int, ...] = field(init=False, repr=False, compare=False)
    #: ``decode(points, order)`` for exactly this tag's points (shared by equal tags)
    decode: Decoder = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # frozen: the precomputed fields are set once here, like a constructor would
        object.__setattr__(self, "request_ids", tuple(sorted({p.request for p in self.pieces})))
        tag = self.tag
        decode = decoder(tag.type, tag.count, self.point_bits, self.bit, self.byte_order)
        if tag.scale is not None:
            decode = _scaled(decode, tag.scale)
        object.__setattr__(self, "decode", decode)

    @property
    def requests(self) -> set[int]:
        return set(self.request_ids)


@dataclass(frozen=True, slots=True)
class TagResult:
    """A tag's value after a scan, or the error that made it unavailable."""

    tag: TagConfig
    value: TagValue | None
    error: PlcError | None


@dataclass(frozen=True, slots=True)
class ScanPlan:
    requests: tuple[ReadRequest, ...]
    tags: tuple[TagPlan, ...]
    #: :meth:`whole_reply_tag`, computed once with the plan (the poller reads it every scan)
    whole_tag: str | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "whole_tag", self.whole_reply_tag())

    def whole_reply_tag(self) -> str | None:
        """The name of the one tag whose value is the whole reply of the one request, as read
        (``raw``, more than one point, no scale, no bit), else None.

        For such a plan :meth:`extract` gives a copy of the reply, so the poller may hand the
        reply itself out as the sample's value (it is a fresh list no one else holds).
        """
        if len(self.requests) != 1 or len(self.tags) != 1:
            return None
        plan = self.tags[0]
        tag, count = plan.tag, self.requests[0].count
        if (
            tag.type is not RAW
            or tag.count < 2
            or tag.scale is not None
            or plan.bit is not None
            or plan.pieces != (Piece(0, 0, count),)
        ):
            return None
        return tag.name

    def tags_of(self, request: int) -> list[TagConfig]:
        return [t.tag for t in self.tags if request in t.request_ids]

    def split(
        self, replies: Sequence[Sequence[int | bool] | PlcError], order: WordOrder
    ) -> list[TagResult]:
        """Tag values from one reply (or error) per request, in request order."""
        if len(replies) != len(self.requests):
            raise ValueError("one reply per request expected")
        out: list[TagResult] = []
        for plan in self.tags:
            result = self.extract(plan, replies, order)
            if isinstance(result, PlcError):
                out.append(TagResult(plan.tag, None, result))
            else:
                out.append(TagResult(plan.tag, result, None))
        return out

    def extract(
        self,
        plan: TagPlan,
        replies: Sequence[Sequence[int | bool] | PlcError],
        order: WordOrder,
    ) -> TagValue | PlcError:
        """One tag's value from one reply (or error) per request, or the error (not raised).

        The poller calls this for every tag of every scan, so the common case (one piece, the
        whole reply) takes no copy and the value comes from a decoder chosen when the plan was
        built.
        """
        pieces = plan.pieces
        points: Sequence[int | bool]
        if len(pieces) == 1:
            piece = pieces[0]
            reply = replies[piece.request]
            if isinstance(reply, PlcError):
                return reply
            request = self.requests[piece.request]
            if len(reply) != request.count:
                return _short(reply, request)
            offset, length = piece.offset, piece.length
            points = (
                reply if offset == 0 and length == len(reply) else reply[offset : offset + length]
            )
            bits_seen = bool(points) and isinstance(points[0], bool)
        else:
            collected: list[int | bool] = []
            bits_seen = False
            for piece in pieces:
                reply = replies[piece.request]
                if isinstance(reply, PlcError):
                    return reply
                request = self.requests[piece.request]
                if len(reply) != request.count:
                    return _short(reply, request)
                part = reply[piece.offset : piece.offset + piece.length]
                bits_seen = bits_seen or (bool(part) and isinstance(part[0], bool))
                collected.extend(part)
            points = collected
        if bits_seen and plan.tag.type not in _BIT_TYPES:
            # A client returns ``list[int]`` or ``list[bool]``, never a mix: one look per piece.
            return AddressError(
                f"type {plan.tag.type.name} cannot be read from a bit area "
                f"(tag {plan.tag.name!r} at {plan.tag.address})"
            )
        try:
            return plan.decode(points, order)
        except PlcError as exc:  # points that are no valid value of the type (a BCD digit > 9)
            return exc.bind(request=f"tag {plan.tag.name!r} at {plan.tag.address}")


def _short(reply: Sequence[int | bool], request: ReadRequest) -> PlcError:
    return RemoteProtocolError(
        f"reply has {len(reply)} points, {request.count} were requested",
        request=_describe(request),
    )


def _describe(request: ReadRequest) -> str:
    return f"read {request.address} x{request.count}"


#: ``decode(points, order) -> value`` of one tag (exactly its points, in read order)
Decoder = Callable[[Sequence[Point], WordOrder], TagValue]

_BIT_TYPES = (RAW, BOOL)
#: struct codes of a point and of a value, for the decoders that go through ``struct``
_POINT_CODE = {8: "B", 16: "H"}
#: types decoded through ``struct`` (by name: KF is an int16, KH and KM are uint16)
_VALUE_CODE = {
    "int8": "b",
    "uint8": "B",
    "int16": "h",
    "kf": "h",
    "uint16": "H",
    "kh": "H",
    "km": "H",
    "int32": "i",
    "uint32": "I",
    "float32": "f",
}
_DECODERS: dict[tuple[ValueType[Any], int, int, int | None, ByteOrder], Decoder] = {}
#: distinct (type, count, point width) decoders kept; beyond that new ones are not cached
_DECODER_CACHE_SIZE = 4096


def decoder(
    dtype: ValueType[Any],
    count: int,
    point_bits: int,
    bit: int | None = None,
    byte_order: ByteOrder = Endian.BIG,
) -> Decoder:
    """The decoder of ``count`` values of ``dtype`` over ``point_bits``-bit points.

    Chosen once per tag when a plan is built (and shared by equal tags of every PLC, so a
    thousand PLCs with the same tags hold one decoder each kind), not per scan. Every decoder
    gives exactly what :meth:`ValueType.decode` gives value by value (property-tested).
    """
    key = (dtype, count, point_bits, bit, byte_order)
    found = _DECODERS.get(key)
    if found is None:
        found = _make_decoder(dtype, count, point_bits, bit, byte_order)
        if len(_DECODERS) < _DECODER_CACHE_SIZE:
            _DECODERS[key] = found
    return found


def _scaled(decode: Decoder, scale: Scale) -> Decoder:
    to_eng = scale.to_eng

    def scaled(points: Sequence[Point], order: WordOrder) -> TagValue:
        value = decode(points, order)
        if isinstance(value, list):
            return [to_eng(v) for v in value]  # type: ignore[arg-type]
        return to_eng(value)  # type: ignore[arg-type]

    return scaled


def _make_decoder(
    dtype: ValueType[Any], count: int, bits: int, bit: int | None, byte_order: ByteOrder
) -> Decoder:
    scalar = count == 1
    if bit is not None:

        def bits_of_word(points: Sequence[Point], order: WordOrder) -> TagValue:
            found: list[bool] = bits_of_points(points, bits, bit, count)
            return found[0] if scalar else list(found)

        return bits_of_word
    if dtype is RAW:
        if scalar:
            return lambda points, order: points[0]
        return lambda points, order: list(points)
    if dtype is BOOL:
        if scalar:
            return lambda points, order: bool(points[0])
        return lambda points, order: [bool(p) for p in points]
    slow = _value_by_value(dtype, count, bits, byte_order)
    point_code, n = _POINT_CODE.get(bits), dtype.points_per_value(bits)
    value_code = _VALUE_CODE.get(dtype.name)
    if value_code is None or point_code is None or dtype.bits < bits or dtype.bits != n * bits:
        return slow  # e.g. int8 in a 16-bit word, or KG/KT/BCD/text: value by value
    # All points of the tag packed as big- or little-endian point words, then unpacked as values:
    # the word order of the PLC family is the byte order of the whole run (MELSEC: low word
    # first = little-endian; S5: big-endian). A point out of range (a client returning signed
    # words, say) makes ``pack`` fail, and the value-by-value path masks it as before.
    pack_big = struct.Struct(f">{n * count}{point_code}").pack
    if value_code == point_code:
        # uint16 in words, uint8 in bytes: the values are the points once they are in range
        # (pack checks that in C); no new int objects.
        def same(points: Sequence[Point], order: WordOrder) -> TagValue:
            try:
                pack_big(*points)
            except struct.error:
                return slow(points, order)
            return points[0] if scalar else list(points)

        return same
    pack_little = struct.Struct(f"<{n * count}{point_code}").pack
    unpack_big = struct.Struct(f">{count}{value_code}").unpack
    unpack_little = struct.Struct(f"<{count}{value_code}").unpack
    big = Endian.BIG

    def fast(points: Sequence[Point], order: WordOrder) -> TagValue:
        try:
            if order is big:
                values: tuple[Scalar, ...] = unpack_big(pack_big(*points))
            else:
                values = unpack_little(pack_little(*points))
        except struct.error:
            return slow(points, order)
        return values[0] if scalar else list(values)

    return fast


def _value_by_value(dtype: ValueType[Any], count: int, bits: int, byte_order: ByteOrder) -> Decoder:
    n = dtype.points_per_value(bits)
    if n == 1 and dtype.kind == "int" and dtype.name in _VALUE_CODE:
        # one point per value (int8 in a word, or a point out of range): mask and sign-extend
        mask = (1 << dtype.bits) - 1
        half, full = 1 << (dtype.bits - 1), 1 << dtype.bits
        signed = dtype.signed

        def masked(points: Sequence[Point], order: WordOrder) -> TagValue:
            values: list[Scalar] = [int(p) & mask for p in points]
            if signed:
                values = [v - full if v >= half else v for v in values]  # type: ignore[operator]
            return values[0] if count == 1 else values

        return masked

    decode = dtype.decode

    def general(points: Sequence[Point], order: WordOrder) -> TagValue:
        values = [
            decode(points[i * n : (i + 1) * n], bits, order, byte_order) for i in range(count)
        ]
        return values[0] if count == 1 else values

    return general


def split_bit(client: Client, address: str) -> tuple[str, int | None]:
    """``(address, bit)`` of a bit-of-a-word address (``D100.3``), else ``(address, None)``."""
    return client.split_bit(address)


def encode_tag(
    tag: TagConfig,
    values: Sequence[object],
    point_bits: int,
    word_order: WordOrder,
    byte_order: ByteOrder,
) -> list[Point]:
    """The points that write ``values`` (one per ``count``) to ``tag``: scaled back to raw and
    encoded; raises :class:`AddressError` (a :class:`~plcstack.errors.ValueEncodeError` for a
    value the type cannot hold) before anything is sent."""
    vtype, scale = tag.type, tag.scale
    if scale is not None:
        values = [scale.to_raw(v, vtype) for v in values]
    return vtype.encode_many(values, point_bits, word_order, byte_order)


def point_bits(client: Client, area: Hashable | None) -> int:
    """Width of one point of ``area`` (``Client.point_bits``); 16 for a client that cannot merge."""
    if area is None:
        return DEFAULT_POINT_BITS
    try:
        return int(client.point_bits(area))
    except NotImplementedError:
        return DEFAULT_POINT_BITS


@dataclass(slots=True)
class _Span:
    tag: TagConfig
    area: Hashable
    start: int
    points: int
    point_bits: int
    bit: int | None = None


def _locate(client: Client, tag: TagConfig) -> _Span | None:
    """``None`` when the client cannot merge; raises AddressError naming the tag."""
    address, bit = client.split_bit(tag.address)
    try:
        area, index = client.locate(address, 1)
        limit = client.max_points(area)
    except NotImplementedError:
        if bit is not None:
            raise AddressError("this client cannot read a bit of a word") from None
        return None
    bits = point_bits(client, area)
    where = f"tag {tag.name!r} at {tag.address}"
    if bit is not None:
        if tag.type is not BOOL:
            raise AddressError(f"{where}: a bit of a word is read as type bool")
        if bits <= 1 or bit >= bits:
            raise AddressError(f"{where}: bit {bit} is not a bit of a {bits}-bit point")
        points = -(-(bit + tag.count) // bits)
    else:
        tag.type.check_area(bits, where)
        points = tag.count * tag.type.points_per_value(bits)
    if points > 1:
        # Make the client check that the last point exists, whatever the frame limit.
        client.locate(client.address_at(area, index + points - 1), 1)
    if limit < 1:
        raise AddressError(f"client reports max_points {limit} for {tag.address}")
    return _Span(tag, area, index, points, bits, bit)


def build_plan(
    client: Client,
    tags: Iterable[TagConfig],
    *,
    max_gap: int = 8,
    isolate: frozenset[str] = frozenset(),
) -> ScanPlan:
    """The requests for ``tags`` on ``client``; tags named in ``isolate`` are not merged.

    Raises :class:`AddressError` (naming the tag) for an address the client refuses.
    """
    requests: list[ReadRequest] = []
    pieces: dict[str, list[Piece]] = {}
    bits_of: dict[str, int] = {}
    bit_of: dict[str, int | None] = {}
    tag_list = list(tags)
    spans: list[_Span] = []
    for tag in tag_list:
        try:
            span = _locate(client, tag)
        except AddressError as exc:
            raise AddressError(
                f"tag {tag.name!r}: {exc.message}",
                plc=client.name,
                request=f"address {tag.address}",
            ) from None
        if span is None:
            n = tag.count * tag.type.points_per_value(DEFAULT_POINT_BITS)
            requests.append(ReadRequest(tag.address, n))
            pieces[tag.name] = [Piece(len(requests) - 1, 0, n)]
            bits_of[tag.name] = DEFAULT_POINT_BITS
        else:
            spans.append(span)
            bits_of[tag.name] = span.point_bits
            bit_of[tag.name] = span.bit
            pieces[tag.name] = []

    # Group by area (areas need not be orderable: keep the first-seen order of areas).
    by_area: dict[Hashable, list[_Span]] = {}
    for span in spans:
        by_area.setdefault(span.area, []).append(span)
    for area, group in by_area.items():
        limit = client.max_points(area)
        group.sort(key=lambda s: (s.start, s.points))
        for batch in _merge(group, limit, max_gap, isolate):
            requests.append(
                ReadRequest(
                    client.address_at(area, batch.start), batch.end - batch.start, area, batch.start
                )
            )
            for name, first, length in batch.members:
                pieces[name].append(Piece(len(requests) - 1, first - batch.start, length))
    byte_order: ByteOrder = getattr(client, "byte_order", Endian.BIG)
    plans = tuple(
        TagPlan(tag, tuple(pieces[tag.name]), bits_of[tag.name], bit_of.get(tag.name), byte_order)
        for tag in tag_list
    )
    return ScanPlan(tuple(requests), plans)


@dataclass(slots=True)
class _Batch:
    """An open request ``[start, end)`` and the (tag, first point, length) pieces it carries."""

    start: int
    end: int
    members: list[tuple[str, int, int]]


def _merge(group: list[_Span], limit: int, max_gap: int, isolate: frozenset[str]) -> list[_Batch]:
    """Greedy merge of spans sorted by start (what fits the open request joins it)."""
    batches: list[_Batch] = []
    current: _Batch | None = None
    for span in group:
        name = span.tag.name
        first, end = span.start, span.start + span.points
        alone = name in isolate
        if alone:
            current = None
        if not alone:
            # Already read whole by an earlier request (an overlap with a long tag)? Then free.
            home = next((b for b in batches if b.start <= first and end <= b.end), None)
            if home is not None:
                home.members.append((name, first, end - first))
                continue
        while first < end:
            # A tag joins the open request only whole: a float32 read half in one frame and half
            # in the next could tear. Only a tag longer than a frame is split.
            if (
                current is not None
                and current.start <= first
                and first - current.end <= max_gap
                and end <= current.start + limit
            ):
                length = end - first
                current.members.append((name, first, length))
                current.end = max(current.end, first + length)
                first += length
                continue
            stop = min(end, first + limit)
            current = _Batch(first, stop, [(name, first, stop - first)])
            batches.append(current)
            first = stop
        if alone:
            current = None
    return batches


def describe(request: ReadRequest) -> str:
    """How a request is named in errors and logs: ``read D100 x10``."""
    return _describe(request)
