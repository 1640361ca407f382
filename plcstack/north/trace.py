"""``[trace]``: the flight recorder of a running poller, as a north-side sink.

```toml
[trace]
ring = 64            # frames kept per PLC, in memory (default 64)
dir = "traces"       # where a PLC's frames are written when it goes offline, relative to
                     # this file (default "traces")
interval = "1h"      # at most one such file per PLC in this time (default one hour)
```

Every PLC's connection records its last ``ring`` frames (:class:`~plcstack.wire.ring.FrameRing`,
what it costs is in ``benchmarks/RESULTS.md``). As a sink the recorder sees every scan and
decides reachability by the one rule of the north side (:class:`~plcstack.north.layout.
Reachability`): when a PLC goes offline its frames are written to ``dir`` as pcapng, at most once
per PLC per ``interval``, and the log line names the file. :meth:`TraceSink.capture` gives a
PLC's frames on request (the REST route ``GET /api/plcs/NAME/capture.pcapng``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from plcstack.checks import Table
from plcstack.clients.base import Client
from plcstack.north.face import FaceBase, PlcUpdate
from plcstack.north.layout import Reachability
from plcstack.poll.samples import Scan
from plcstack.wire.ring import DEFAULT_RING, MIN_INTERVAL, FlightRecorder

__all__ = ["MAX_RING", "TraceSettings", "TraceSink", "parse_trace"]

#: the most frames a ring may keep: a PLC's last few seconds at any poll rate, not a capture
#: (``--pcap`` is for that); 4096 frames of up to 4 KiB bound a ring at 16 MiB
MAX_RING = 4096
_KEYS = ("ring", "dir", "interval")


@dataclass(frozen=True)
class TraceSettings:
    #: frames kept per PLC
    ring: int = DEFAULT_RING
    #: where the automatic captures go (a relative path was taken relative to the TOML file)
    directory: Path = Path("traces")
    #: seconds between two automatic captures of one PLC
    interval: float = MIN_INTERVAL


def parse_trace(table: object, *, base: Path | None = None) -> TraceSettings:
    """The ``[trace]`` table; ``base`` = the TOML file's directory, for a relative ``dir``."""
    t = Table.of(table, "trace", base=base)
    t.keys(_KEYS)
    ring = t.integer("ring", DEFAULT_RING, 1, MAX_RING)
    directory = t.file("dir", "traces", what="a folder") or "traces"
    interval = t.seconds("interval", MIN_INTERVAL, hi=math.inf)
    return TraceSettings(ring, Path(directory), interval)


class PlcConnections(Protocol):
    """What the recorder needs of a poller: its PLCs and each one's client."""

    @property
    def plcs(self) -> list[str]: ...

    def client(self, plc: str) -> Client: ...


class TraceSink(FaceBase):
    """The flight recorder of one poller: rings on its PLCs' connections, a capture file when
    one goes offline. A sink (``submit(scans)``) of the north side."""

    #: how logs, metrics and ``/healthz`` name it
    name = "flight recorder"

    def __init__(self, settings: TraceSettings) -> None:
        self.settings = settings
        self.recorder = FlightRecorder(
            size=settings.ring, directory=settings.directory, min_interval=settings.interval
        )
        self._reachability = Reachability()
        #: files written because a PLC went offline
        self.written: list[Path] = []

    def attach(self, poller: PlcConnections) -> None:
        """Record every PLC's connection of ``poller`` from its next connect on."""
        for plc in poller.plcs:
            poller.client(plc).transport.record_to(self.recorder.ring(plc))

    async def update_plcs(self, update: PlcUpdate) -> None:
        """Record the connections of the PLCs a reload added or changed (a changed URL is a
        new connection) from their next connect on."""
        view = update.view
        for plc in (*update.added, *update.changed):
            view.client(plc).transport.record_to(self.recorder.ring(plc))

    def submit(self, scans: Sequence[Scan]) -> None:
        for scan in scans:
            if self._reachability.update(scan) is False:
                path = self.recorder.offline(scan.plc)
                if path is not None:
                    self.written.append(path)

    def capture(self, plc: str) -> bytes:
        """``plc``'s last frames as pcapng (a file without packets before its first)."""
        return self.recorder.ring(plc).pcapng()
