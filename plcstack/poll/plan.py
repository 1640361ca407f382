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

from collections.abc import Hashable, Iterable, Sequence
from dataclasses import dataclass

from plcstack.clients.base import Client
from plcstack.errors import AddressError, PlcError, RemoteProtocolError
from plcstack.poll.config import TagConfig
from plcstack.poll.values import DataType, Scalar, TagValue, WordOrder

__all__ = [
    "Piece",
    "ReadRequest",
    "ScanPlan",
    "TagPlan",
    "TagResult",
    "build_plan",
    "describe",
    "point_bits",
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

    @property
    def requests(self) -> set[int]:
        return {p.request for p in self.pieces}


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

    def tags_of(self, request: int) -> list[TagConfig]:
        return [t.tag for t in self.tags if request in t.requests]

    def split(
        self, replies: Sequence[Sequence[int | bool] | PlcError], order: WordOrder
    ) -> list[TagResult]:
        """Tag values from one reply (or error) per request, in request order."""
        if len(replies) != len(self.requests):
            raise ValueError("one reply per request expected")
        out: list[TagResult] = []
        for plan in self.tags:
            error: PlcError | None = None
            points: list[int | bool] = []
            for piece in plan.pieces:
                reply = replies[piece.request]
                if isinstance(reply, PlcError):
                    error = reply
                    break
                expected = self.requests[piece.request].count
                if len(reply) != expected:
                    error = RemoteProtocolError(
                        f"reply has {len(reply)} points, {expected} were requested",
                        request=_describe(self.requests[piece.request]),
                    )
                    break
                points.extend(reply[piece.offset : piece.offset + piece.length])
            multi_bit = plan.tag.type not in (DataType.RAW, DataType.BOOL)
            if error is None and multi_bit and any(isinstance(p, bool) for p in points):
                error = AddressError(
                    f"type {plan.tag.type.value} cannot be read from a bit area "
                    f"(tag {plan.tag.name!r} at {plan.tag.address})"
                )
            if error is not None:
                out.append(TagResult(plan.tag, None, error))
                continue
            out.append(TagResult(plan.tag, _decode(plan, points, order), None))
        return out


def _describe(request: ReadRequest) -> str:
    return f"read {request.address} x{request.count}"


def _decode(plan: TagPlan, points: Sequence[int | bool], order: WordOrder) -> TagValue:
    dtype = plan.tag.type
    count = plan.tag.count
    values: list[Scalar]
    if dtype is DataType.RAW:
        values = list(points)
    elif dtype is DataType.BOOL:
        values = [bool(p) for p in points]
    elif dtype.points_per_value(plan.point_bits) == 1 and dtype is not DataType.FLOAT32:
        # the common case (int16/uint16 on words, uint8/int8 on bytes): one point per value
        mask = (1 << dtype.bits) - 1
        if dtype.signed:
            half, full = 1 << (dtype.bits - 1), 1 << dtype.bits
            values = [v - full if v >= half else v for v in (int(p) & mask for p in points)]
        else:
            values = [int(p) & mask for p in points]
    else:
        n = dtype.points_per_value(plan.point_bits)
        values = [
            dtype.decode(points[i * n : (i + 1) * n], plan.point_bits, order) for i in range(count)
        ]
    return values[0] if count == 1 else values


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


def _locate(client: Client, tag: TagConfig) -> _Span | None:
    """``None`` when the client cannot merge; raises AddressError naming the tag."""
    try:
        area, index = client.locate(tag.address, 1)
        limit = client.max_points(area)
    except NotImplementedError:
        return None
    bits = point_bits(client, area)
    tag.type.check_area(bits, f"tag {tag.name!r} at {tag.address}")
    points = tag.count * tag.type.points_per_value(bits)
    if points > 1:
        # Make the client check that the last point exists, whatever the frame limit.
        client.locate(client.address_at(area, index + points - 1), 1)
    if limit < 1:
        raise AddressError(f"client reports max_points {limit} for {tag.address}")
    return _Span(tag, area, index, points, bits)


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
    plans = tuple(TagPlan(tag, tuple(pieces[tag.name]), bits_of[tag.name]) for tag in tag_list)
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
