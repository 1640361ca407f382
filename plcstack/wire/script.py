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

Two fields are numbers a client counts, not part of what it asks, and are compared as any
value: the S5-LAN block's ``UserCode`` (plcstack's client numbers its requests there; the
module echoes it, and so does the replay, into the recorded answer) and the MK header's
``SeqNo`` of each telegram (every side numbers what it sends; receivers do not check it by
default). Without that a replay of either could never start a second round.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from plcstack.codecs import mk, s5lan
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
    #: what to send: the exchange's recorded answers, echo fields as the request has them
    answers: tuple[bytes, ...] = ()
    nearest: bytes = b""
    differs_at: int = 0


#: where an S5-LAN block's UserCode is (A.2: bytes 18-21 of request and answer alike)
_USER_CODE = slice(18, 22)
_S5LAN_TYPES = (s5lan.PLC_TYPE, s5lan.PLC_TYPE_NUMERIC)


def _is_s5lan(data: bytes) -> bool:
    return len(data) > 4 and data[0] in _S5LAN_TYPES and data[4] == s5lan.HEADER_LEN


def comparable(data: bytes) -> bytes:
    """``data`` with the counted fields zeroed: S5-LAN's UserCode, each MK telegram's SeqNo
    (a partial request: as far as its fields reach)."""
    if _is_s5lan(data) and len(data) > _USER_CODE.start:
        out = bytearray(data)
        out[_USER_CODE] = bytes(len(out[_USER_CODE]))
        return bytes(out)
    if data.startswith(mk.MAGIC):
        out = bytearray(data)
        at = 0
        while at + mk.HEADER_LEN <= len(out) and out[at : at + 2] == mk.MAGIC:
            out[at + 6 : at + 8] = b"\x00\x00"
            at += mk.HEADER_LEN + int.from_bytes(out[at + 2 : at + 4], "little")
        return bytes(out)
    return data


def _echoed(request: bytes, answers: tuple[bytes, ...]) -> tuple[bytes, ...]:
    """The recorded answers, with an S5-LAN answer's UserCode the request's (A.2: echoed)."""
    if not (_is_s5lan(request) and len(request) >= s5lan.HEADER_LEN and answers):
        return answers
    first = answers[0]
    if not (_is_s5lan(first) and len(first) >= s5lan.HEADER_LEN):
        return answers
    echoed = first[: _USER_CODE.start] + request[_USER_CODE] + first[_USER_CODE.stop :]
    return (echoed, *answers[1:])


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
        self._keys = [comparable(e.request) for e in exchanges]
        self._used = [False] * len(exchanges)
        self._first_unused = 0
        #: rounds begun (1 while the first is under way), requests answered, mismatches
        self.rounds = 1
        self.answered = 0
        self.mismatches = 0

    def _search(self, key: bytes) -> tuple[int, bool] | None:
        used, keys = self._used, self._keys
        for index in range(self._first_unused, len(keys)):
            if used[index]:
                continue
            request = keys[index]
            if key.startswith(request):
                return index, True
            if request.startswith(key):
                return index, False
        return None

    def match(self, data: bytes) -> Match:
        """Decide on ``data``, the bytes received and not yet answered."""
        key = comparable(data)
        found = self._search(key)
        if (
            found is None
            and self.repeat
            and self._first_unused > 0
            and any(key.startswith(k) or k.startswith(key) for k in self._keys)
        ):
            self._used = [False] * len(self.exchanges)
            self._first_unused = 0
            self.rounds += 1
            found = self._search(key)
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
        taken = len(exchange.request)
        return Match("answer", exchange, taken, answers=_echoed(data[:taken], exchange.answers))

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
