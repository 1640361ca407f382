"""What the replay answers: the recorded exchanges of one server, matched by request bytes,
in order (Sans-IO: bytes in, the decision out).

A request is answered with the first exchange, in capture order, not yet used in this round
whose recorded request its bytes are: the poller's requests come back in the order it sent
them, and requests that are the same bytes (the same scan, again and again) take their
recorded answers one after the other. When bytes received so far are only the start of that
request (a request split over several reads, or the AS511 dialogue's byte-by-byte steps), the
replay waits for the rest. When every recorded exchange has been used, a new round begins
with the first (unless ``repeat`` is off), so a replay serves as long as it is polled.

A request that no recorded exchange is (nor begins) is a mismatch: the replay does not guess
an answer. The caller closes the connection (UDP: answers nothing) and reports it, naming the
recorded request nearest to it and the first byte where they differ.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from plcstack.wire.streams import Exchange

__all__ = ["Match", "Script"]


@dataclass(frozen=True, slots=True)
class Match:
    """The decision on the bytes received: ``answer`` (the exchange, and how many of the
    bytes its request took), ``wait`` for more, or ``mismatch`` (the nearest recorded
    request, and the offset of the first byte that differs from it)."""

    kind: Literal["answer", "wait", "mismatch"]
    exchange: Exchange | None = None
    taken: int = 0
    nearest: bytes = b""
    differs_at: int = 0


def _common(a: bytes, b: bytes) -> int:
    n = min(len(a), len(b))
    for i in range(n):
        if a[i] != b[i]:
            return i
    return n


class Script:
    """The exchanges of one recorded server and where the replay stands in them."""

    def __init__(self, name: str, exchanges: list[Exchange], *, repeat: bool = True) -> None:
        self.name = name
        self.exchanges = exchanges
        self.repeat = repeat
        self._used = [False] * len(exchanges)
        self._first_unused = 0
        #: rounds begun (1 while the first is under way), requests answered, mismatches
        self.rounds = 1
        self.answered = 0
        self.mismatches = 0

    def _search(self, data: bytes) -> tuple[int, bool] | None:
        used = self._used
        for index in range(self._first_unused, len(self.exchanges)):
            if used[index]:
                continue
            request = self.exchanges[index].request
            if data.startswith(request):
                return index, True
            if request.startswith(data):
                return index, False
        return None

    def match(self, data: bytes) -> Match:
        """Decide on ``data``, the bytes received and not yet answered."""
        found = self._search(data)
        if (
            found is None
            and self.repeat
            and self._first_unused > 0
            and any(
                data.startswith(e.request) or e.request.startswith(data) for e in self.exchanges
            )
        ):
            self._used = [False] * len(self.exchanges)
            self._first_unused = 0
            self.rounds += 1
            found = self._search(data)
        if found is None:
            self.mismatches += 1
            return self._mismatch(data)
        index, complete = found
        if not complete:
            return Match("wait")
        self._used[index] = True
        while self._first_unused < len(self._used) and self._used[self._first_unused]:
            self._first_unused += 1
        self.answered += 1
        exchange = self.exchanges[index]
        return Match("answer", exchange, len(exchange.request))

    def _mismatch(self, data: bytes) -> Match:
        best = b""
        best_common = -1
        for index in range(len(self.exchanges)):
            request = self.exchanges[(self._first_unused + index) % len(self.exchanges)].request
            common = _common(data, request)
            if common > best_common:
                best, best_common = request, common
        return Match("mismatch", nearest=best, differs_at=max(best_common, 0))

    @property
    def finished(self) -> bool:
        """Every exchange of the round has been used (and no new round will begin)."""
        return self._first_unused >= len(self.exchanges) and not self.repeat
