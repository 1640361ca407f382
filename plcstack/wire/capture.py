"""``--pcap FILE``: a pcapng file the tap writes as the traffic goes.

Flushed as it goes: blocks are written at once into the file's buffer, and the file is
flushed ``FLUSH_DELAY`` (0.1 s) after the first block that is not yet on disk (at once where no
loop runs), so a capture that is copied while the command still runs, or whose process is
killed, holds everything but the last tenth of a second. A flush per request cost a system call
per request (measured: ``benchmarks/wire_capture.py``); one per 0.1 s costs nothing a poll
notices.

Bounded by size: when the next blocks would take the file beyond ``limit`` bytes, the file is
rotated: it becomes ``FILE.1`` (replacing an older one) and a fresh ``FILE`` starts, with its
own header and a synthesised handshake for each TCP connection still open, so each of the two
files opens on its own in Wireshark. At most about twice the limit is on disk. The first
rotation is logged as a warning, later ones at INFO.

A write that fails (a full disk, a removed directory) stops the capture, not the command: it
is logged once, every later packet is counted as lost, and :attr:`PcapngCapture.failure` says
what happened so the command reports it and exits non-zero at its end.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from pathlib import Path
from typing import BinaryIO, Final

from plcstack.transports.tap import ConnectionTap, Endpoints
from plcstack.wire.packets import MAX_SEGMENT
from plcstack.wire.recording import Recording, Stream

__all__ = ["DEFAULT_LIMIT", "FLUSH_DELAY", "PcapngCapture", "parse_size"]

log = logging.getLogger(__name__)

#: bytes a capture file may reach before it is rotated (``--pcap-limit``)
DEFAULT_LIMIT: Final = 100 * 1024 * 1024
#: seconds from the first block not yet flushed to the flush
FLUSH_DELAY: Final = 0.1
#: the least limit that makes sense: a header and a few packets
MIN_LIMIT: Final = 4096

#: bytes one packet's block takes beyond its payload at most: the EPB (32), its options
#: (flags 8, end 4), an IPv6 header (40) and a TCP one (20), padding (3)
_PACKET_BOUND: Final = 110
#: bytes of the blocks an open or an end takes at most: a serial line's interface, or three
#: TCP packets with a comment
_EVENT_BOUND: Final = 3 * _PACKET_BOUND + 256

_UNITS: Final = {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3}


def parse_size(text: str) -> int:
    """``100M``, ``512k``, ``2G`` or a number of bytes; at least 4 KiB."""
    value = text.strip().lower().removesuffix("b").removesuffix("i")
    unit = value[-1:] if value[-1:] in _UNITS and value[-1:] else ""
    number = value[: len(value) - len(unit)]
    try:
        size = int(float(number) * _UNITS[unit])
    except ValueError:
        raise ValueError(f"{text!r} is not a size like 100M, 512k or 2G") from None
    if size < MIN_LIMIT:
        raise ValueError(f"{text!r} is below the least capture size, 4k")
    return size


def _micros() -> int:
    return time.time_ns() // 1000


class PcapngCapture:
    """A :class:`~plcstack.transports.tap.Tap` that writes a pcapng file at ``path``.

    ``open()`` creates the file (raises ``OSError``: the caller's usage error); ``close()``
    flushes and closes it. Connections recorded after ``close()`` are dropped silently: the
    command has ended.
    """

    def __init__(self, path: str | Path, *, limit: int = DEFAULT_LIMIT) -> None:
        self.path = Path(path)
        self.limit = limit
        self._recording = Recording()
        self._file: BinaryIO | None = None
        self._size = 0
        self._flush_pending = False
        self._closed = False
        #: packets written, and packets lost because the capture had failed
        self.packets = 0
        self.lost = 0
        self.rotations = 0
        #: why the capture stopped before the command ended (None: it did not)
        self.failure: str | None = None

    # -- life cycle --------------------------------------------------------------------------
    def open(self) -> PcapngCapture:
        self._file = self.path.open("wb")
        self._write_raw(self._recording.header())
        self._flush()
        return self

    def close(self) -> None:
        self._closed = True
        file, self._file = self._file, None
        if file is None:
            return
        try:
            file.close()  # flushes
        except OSError as exc:
            self._fail(exc)

    def __enter__(self) -> PcapngCapture:
        return self.open() if self._file is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the tap -----------------------------------------------------------------------------
    def connection(self, endpoints: Endpoints) -> ConnectionTap:
        ready = self._ready(_EVENT_BOUND)
        stream, blocks = self._recording.open(endpoints, _micros())
        if ready:
            self._write(blocks, 0)
        return _CaptureConnection(self, stream)

    def record(self, stream: Stream, outbound: bool, data: bytes) -> None:
        segments = 1 + len(data) // MAX_SEGMENT
        ready = self._ready(len(data) + segments * _PACKET_BOUND)
        blocks = self._recording.data(stream, outbound, data, _micros())
        if ready:
            self._write(blocks, 1)
        elif blocks and self.failure is not None:
            self.lost += 1

    def end(self, stream: Stream, by_peer: bool) -> None:
        ready = self._ready(_EVENT_BOUND)
        blocks = self._recording.end(stream, by_peer, _micros())
        if ready:
            self._write(blocks, 0)

    # -- writing -----------------------------------------------------------------------------
    def _ready(self, bound: int) -> bool:
        """Whether the blocks of the next event (at most ``bound`` bytes) can be written,
        rotating first when they would take the file beyond its limit. Decided before the
        event is turned into blocks: a rotation starts the new file with the connections'
        state before that event, which the event's own blocks then continue."""
        if self._closed or self._file is None:
            return False
        if self._size + bound > self.limit and self._size > 0:
            self._rotate()
        return self._file is not None

    def _write(self, blocks: bytes, packets: int) -> None:
        if not blocks:
            return
        self._write_raw(blocks)
        self.packets += packets
        if not self._flush_pending:
            self._flush_pending = True
            try:
                asyncio.get_running_loop().call_later(FLUSH_DELAY, self._flush)
            except RuntimeError:  # no loop: flush now
                self._flush()

    def _write_raw(self, blocks: bytes) -> None:
        file = self._file
        if file is None:
            return
        try:
            file.write(blocks)
        except OSError as exc:
            self._fail(exc)
            return
        self._size += len(blocks)

    def _flush(self) -> None:
        self._flush_pending = False
        file = self._file
        if file is None:
            return
        try:
            file.flush()
        except OSError as exc:
            self._fail(exc)

    def _rotate(self) -> None:
        file, self._file = self._file, None
        older = self.path.with_name(self.path.name + ".1")
        try:
            if file is not None:
                file.close()
            os.replace(self.path, older)
            self._file = self.path.open("wb")
        except OSError as exc:
            self._fail(exc)
            return
        self.rotations += 1
        self._size = 0
        level = logging.WARNING if self.rotations == 1 else logging.INFO
        log.log(
            level,
            "capture %s reached its limit of %d bytes: it continues in a fresh %s, the "
            "previous part is kept as %s (older parts are replaced)",
            self.path,
            self.limit,
            self.path.name,
            older.name,
        )
        self._write_raw(self._recording.resume(_micros()))

    def _fail(self, exc: OSError) -> None:
        if self.failure is None:
            reason = exc.strerror or str(exc)
            self.failure = f"capture {self.path} stopped: {reason}"
            log.error("%s; later packets are not recorded", self.failure)
        file, self._file = self._file, None
        if file is not None:
            with contextlib.suppress(OSError):  # the failure is said; a second adds nothing
                file.close()


class _CaptureConnection:
    """One connection's recorder: tells the capture each event with its stream."""

    __slots__ = ("capture", "stream")

    def __init__(self, capture: PcapngCapture, stream: Stream) -> None:
        self.capture = capture
        self.stream = stream

    def sent(self, data: bytes) -> None:
        self.capture.record(self.stream, True, data)

    def received(self, data: bytes) -> None:
        self.capture.record(self.stream, False, data)

    def ended(self, by_peer: bool) -> None:
        self.capture.end(self.stream, by_peer)
