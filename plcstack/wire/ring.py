"""The flight recorder: the last N frames of each PLC in memory, written out as pcapng when
asked (the web console, ``GET /api/plcs/NAME/capture.pcapng``) and when the PLC goes offline.

A :class:`FrameRing` is one PLC's tap (``transport.record_to(ring)``): each chunk sent or
received is kept as (time, connection, direction, bytes) in a ring of ``size`` frames, the
oldest dropped first; nothing is encoded until a capture is asked for. Memory is bounded by
``size`` frames of at most one receive each (4 KiB on TCP). What a recorded frame costs is
measured in ``benchmarks/`` (the fleet case with and without ``[trace] ring = 64``).

:class:`FlightRecorder` holds the rings of a poller's PLCs and writes a PLC's ring to a file
when it goes offline, at most once per PLC per ``min_interval`` (an hour): a PLC that flaps
does not fill the disk, and the operator is told once where the frames are.
"""

from __future__ import annotations

import collections
import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from plcstack.transports.tap import ConnectionTap, Endpoints
from plcstack.wire.recording import Recording, Stream

__all__ = ["DEFAULT_RING", "FlightRecorder", "FrameRing"]

log = logging.getLogger(__name__)

#: frames a ring keeps when ``[trace] ring`` does not say
DEFAULT_RING: Final = 64
#: the clock of the frames (wall clock: a capture's timestamps), looked up once
_now = time.time_ns

#: seconds between two automatic captures of one PLC
MIN_INTERVAL: Final = 3600.0


@dataclass(slots=True, eq=False)
class _Connection:
    """One recorded connection of a ring: its endpoints, when it opened and ended."""

    endpoints: Endpoints
    opened: int
    ended: int | None = None
    by_peer: bool = False


class _RingConnection:
    __slots__ = ("connection", "received_key", "ring", "sent_key")

    def __init__(self, connection: _Connection, key: int, ring: FrameRing) -> None:
        self.connection = connection
        self.ring = ring
        #: the frame's connection key and direction in one number: key * 2 + (1 if sent)
        self.sent_key = 2 * key + 1
        self.received_key = 2 * key

    def sent(self, data: bytes) -> None:
        ring = self.ring
        ring.times.append(_now())
        ring.keys.append(self.sent_key)
        ring.data.append(data)

    def received(self, data: bytes) -> None:
        ring = self.ring
        ring.times.append(_now())
        ring.keys.append(self.received_key)
        ring.data.append(data)

    def ended(self, by_peer: bool) -> None:
        if self.connection.ended is None:
            self.connection.ended = time.time_ns()
            self.connection.by_peer = by_peer


class FrameRing:
    """The last ``size`` frames of one PLC: a :class:`~plcstack.transports.tap.Tap`.

    A frame is kept in three rings of the same length (its time, its connection and
    direction as one number, its bytes) rather than as one tuple: numbers and bytes are
    no work for the garbage collector, where a tuple per frame made the young collections of
    a 500-PLC poller four times as many (measured with ``benchmarks``' fleet ``ring`` kind).
    """

    def __init__(self, size: int = DEFAULT_RING) -> None:
        if size < 1:
            raise ValueError(f"a ring keeps at least 1 frame, not {size}")
        self.size = size
        self.times: collections.deque[int] = collections.deque(maxlen=size)
        self.keys: collections.deque[int] = collections.deque(maxlen=size)
        self.data: collections.deque[bytes] = collections.deque(maxlen=size)
        self._connections: dict[int, _Connection] = {}
        self._next_key = 0

    def connection(self, endpoints: Endpoints) -> ConnectionTap:
        # connections no frame in the ring refers to any more are let go
        held = {key >> 1 for key in self.keys}
        self._connections = {k: c for k, c in self._connections.items() if k in held}
        key = self._next_key
        self._next_key += 1
        connection = self._connections[key] = _Connection(endpoints, time.time_ns())
        return _RingConnection(connection, key, self)

    def __len__(self) -> int:
        return len(self.data)

    @property
    def frames(self) -> list[tuple[int, int, bool, bytes]]:
        """The frames kept, oldest first: (time in ns, connection key, sent by us, bytes)."""
        return [
            (nanos, key >> 1, bool(key & 1), data)
            for nanos, key, data in zip(self.times, self.keys, self.data, strict=True)
        ]

    def pcapng(self) -> bytes:
        """The frames in the ring as a pcapng file: each connection opens with its handshake
        (synthesised at its first frame in the ring when it began before), and the ones that
        ended in the ring's time close with their FIN exchange."""
        frames = self.frames
        recording = Recording()
        out = [recording.header()]
        streams: dict[int, tuple[_Connection, Stream]] = {}
        first = frames[0][0] if frames else 0
        for nanos, key, sent, data in frames:
            known = streams.get(key)
            if known is None:
                connection = self._connections[key]
                resumed = connection.opened < first
                stream, blocks = recording.open(
                    connection.endpoints, max(connection.opened, first) // 1000, resumed=resumed
                )
                known = streams[key] = (connection, stream)
                out.append(blocks)
            out.append(recording.data(known[1], sent, data, nanos // 1000))
        for connection, stream in streams.values():
            if connection.ended is not None:
                out.append(recording.end(stream, connection.by_peer, connection.ended // 1000))
        return b"".join(out)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "plc"


@dataclass
class FlightRecorder:
    """The rings of a poller's PLCs, and the automatic capture of one that goes offline."""

    size: int = DEFAULT_RING
    #: where the automatic captures go (made when the first is written)
    directory: Path = Path("traces")
    min_interval: float = MIN_INTERVAL
    clock: Callable[[], float] = time.monotonic
    rings: dict[str, FrameRing] = field(default_factory=dict)
    _written: dict[str, float] = field(default_factory=dict)

    def ring(self, plc: str) -> FrameRing:
        """``plc``'s ring (made on first use)."""
        ring = self.rings.get(plc)
        if ring is None:
            ring = self.rings[plc] = FrameRing(self.size)
        return ring

    def capture(self, plc: str) -> bytes:
        """``plc``'s frames as pcapng; ``KeyError`` for a PLC without a ring."""
        return self.rings[plc].pcapng()

    def offline(self, plc: str) -> Path | None:
        """``plc`` went offline: write its ring to ``directory`` unless that was done less
        than ``min_interval`` ago (or the ring is empty); returns the file written. A file
        that cannot be written is logged, never raised: the poller goes on."""
        ring = self.rings.get(plc)
        if ring is None or not ring.frames:
            return None
        now = self.clock()
        last = self._written.get(plc)
        if last is not None and now - last < self.min_interval:
            return None
        self._written[plc] = now
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        path = self.directory / f"{_safe(plc)}-{stamp}.pcapng"
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            path.write_bytes(ring.pcapng())
        except OSError as exc:
            log.error(
                "%s went offline; its last %d frames could not be written to %s: %s",
                plc,
                len(ring),
                path,
                exc.strerror or exc,
            )
            return None
        log.warning(
            "%s went offline: its last %d frames are in %s (open it in Wireshark; at most one "
            "such file per PLC per %d minutes)",
            plc,
            len(ring),
            path,
            round(self.min_interval / 60),
        )
        return path
