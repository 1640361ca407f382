"""AS511 framing (spec part B.3): control characters, fixed frames and DLE transparency.

Both machines of :mod:`plcstack.codecs.as511` and :mod:`plcstack.diagnose` take the control
characters from here; :class:`Unstuffer` de-stuffs a data frame incrementally (byte by byte or a
run at a time).
"""

from __future__ import annotations

from plcstack.errors import RemoteProtocolError

__all__ = [
    "ACCEPT_FRAME",
    "ACK",
    "DC2",
    "DLE",
    "DLE_ACK",
    "DLE_NAK",
    "EOT",
    "ETX",
    "NAK",
    "STX",
    "SYN",
    "TERMINATE_BYTES",
    "TERMINATE_FRAME",
    "Unstuffer",
    "stuff",
    "unstuff",
]

STX = 0x02
ETX = 0x03
EOT = 0x04
ACK = 0x06
DLE = 0x10
NAK = 0x15
SYN = 0x16
DC2 = 0x12
#: [R] D.B4: the PG accepts 11h/12h/14h (or no byte) as terminate byte; the AG sends DC2
TERMINATE_BYTES = frozenset({0x11, 0x12, 0x14})

DLE_ACK = bytes([DLE, ACK])
_DLE_BYTE = bytes([DLE])
_DLE_PAIR = bytes([DLE, DLE])
#: ``DLE end`` for the frame ends in use (ETX: data frames, EOT: parameter frames)
_END_SEQ = {end: bytes([DLE, end]) for end in range(256)}
DLE_NAK = bytes([DLE, NAK])
ACCEPT_FRAME = bytes([SYN, DLE, ETX])
TERMINATE_FRAME = bytes([DC2, DLE, ETX])


# -- DLE transparency (B.3) ------------------------------------------------------------------
def stuff(data: bytes) -> bytes:
    """Double every 10h data byte (B.3)."""
    return bytes(data).replace(b"\x10", b"\x10\x10")


def unstuff(frame: bytes, end: int = ETX) -> bytes:
    """Decode one complete stuffed frame ending in ``DLE end``; raises RemoteProtocolError."""
    decoder = Unstuffer(end)
    for i, byte in enumerate(frame):
        if decoder.feed(byte):
            if i != len(frame) - 1:
                raise RemoteProtocolError("bytes after the end of an AS511 frame")
            return decoder.payload()
    raise RemoteProtocolError("AS511 frame without DLE ETX/EOT end")


class Unstuffer:
    """Incremental de-stuffer of one frame: ``feed(byte)`` returns True at ``DLE end``."""

    __slots__ = ("_buf", "_dle", "end", "limit")

    def __init__(self, end: int, limit: int | None = None) -> None:
        self.end = end
        self.limit = limit
        self._buf = bytearray()
        self._dle = False

    def feed(self, byte: int) -> bool:
        if self._dle:
            self._dle = False
            if byte == DLE:
                self._buf.append(DLE)
            elif byte == self.end:
                return True
            else:
                raise RemoteProtocolError(
                    f"DLE followed by {byte:02X}h inside a frame (expected 10h or {self.end:02X}h)"
                )
        elif byte == DLE:
            self._dle = True
        else:
            self._buf.append(byte)
        if self.limit is not None and len(self._buf) > self.limit:
            raise RemoteProtocolError(f"AS511 frame longer than {self.limit} bytes")
        return False

    def feed_from(self, data: bytes, start: int) -> int:
        """:meth:`feed` every byte of ``data[start:]`` until the frame ends, a run between two
        DLEs at a time; returns the index just after ``DLE end``, or ``-1`` when all of
        ``data`` was consumed without it. Raises exactly where :meth:`feed` would."""
        buf, limit, end, n = self._buf, self.limit, self.end, len(data)
        if not buf and not self._dle:
            # The usual case: the whole frame in this chunk, from its first byte. Find its end
            # (the first DLE end whose DLE is not the second of a pair) and un-stuff it with
            # two ``bytes.replace``; anything unusual (a lone DLE, too long, no end yet) goes
            # the run-by-run loop below from the same start, which decides and raises.
            tail = _END_SEQ[end]
            k = data.find(tail, start)
            while k >= 0:
                j = k
                while j > start and data[j - 1] == DLE:
                    j -= 1
                if not (k - j) & 1:
                    break  # an even number of DLEs before it: this DLE is the frame's end
                k = data.find(tail, k + 2)
            if k >= 0:
                body = data[start:k]
                if _DLE_BYTE not in body.replace(_DLE_PAIR, b""):
                    payload = body.replace(_DLE_PAIR, _DLE_BYTE)
                    if limit is None or len(payload) <= limit:
                        buf += payload
                        return k + 2
        i = start
        while i < n:
            if self._dle:
                self._dle = False
                byte = data[i]
                i += 1
                if byte == DLE:
                    buf.append(DLE)
                elif byte == end:
                    return i
                else:
                    raise RemoteProtocolError(
                        f"DLE followed by {byte:02X}h inside a frame (expected 10h or {end:02X}h)"
                    )
            else:
                j = data.find(_DLE_BYTE, i)
                if j < 0:
                    j = n
                buf += data[i:j]
                if j < n:
                    self._dle = True
                    j += 1
                i = j
            if limit is not None and len(buf) > limit:
                raise RemoteProtocolError(f"AS511 frame longer than {limit} bytes")
        return -1

    def payload(self) -> bytes:
        return bytes(self._buf)

    def __len__(self) -> int:
        return len(self._buf)
