"""The one protocol of the north side: what every face and sink is, and what it is given.

A *face* is anything the runtime feeds with scans: a sink that sends them on (stdout lines, MQTT
JSON, Sparkplug B) or a server that answers its own clients from them (OPC UA, Modbus TCP, the
web console, the metrics endpoint). Each implements :class:`Face`, in the shape of anyio's
``AsyncResource``:

* ``await start()`` makes it serve (listen, connect); it raises a :class:`~plcstack.errors.
  PlcError` (a ``ConfigError`` for a port taken, a certificate unreadable) naming what cannot
  start, and the run ends with exit 2;
* ``submit(scans)`` takes the scans of a batch after report-by-exception (never blocks: a
  sink queues, a server applies them to what its clients read); ``probe(sample)`` raises for a
  sample ``submit`` could not take, without side effects, so the run's supervisor finds the one
  sample a batch failed on;
* ``health()`` says how it is (:class:`~plcstack.north.health.Health`), ``summary()`` what it
  did (one line for stderr at the end of a run), ``announce()`` where a client finds it (said
  on stderr once every PLC's first scan is in, so a client that connects then reads values),
  ``metrics()`` its own figures for ``/metrics`` (prometheus-client metric families);
* ``await update_plcs(update)`` tells it which PLCs a reload added, removed or changed
  (:class:`PlcUpdate`, after the poller applied them: the poller view already shows the new
  PLCs and tags); it makes the PLCs it serves match, and leaves every other PLC as it was;
* ``await aclose()`` stops it; a second call does nothing.

A face is built with what it needs passed in (:mod:`plcstack.north.faces` builds each from the
configuration): the run's one write path, its supervisor (every task of a face runs under it),
the poller's read view (:class:`PollerView`) and the run's health. No face probes another with
``hasattr``/``getattr``, sets attributes on it after it is built, or reaches its private state.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from plcstack.clients.base import Client
from plcstack.north.health import Health
from plcstack.poll.config import PollConfig, TagConfig
from plcstack.poll.samples import Sample, Scan
from plcstack.poll.stats import PlcStats

if TYPE_CHECKING:
    from prometheus_client.core import Metric

__all__ = ["Face", "FaceBase", "PlcUpdate", "PollerView", "ScanSource"]


class PollerView(Protocol):
    """What the north side reads of the poller (a :class:`~plcstack.poll.engine.Poller`, or a
    scale-out :class:`~plcstack.scale.worker.Worker` for the PLCs it holds), and its writes."""

    @property
    def config(self) -> PollConfig: ...

    @property
    def plcs(self) -> list[str]: ...

    def tags(self, plc: str) -> dict[str, tuple[TagConfig, int]]:
        """Each tag of one PLC with the width of its points in bits."""
        ...

    @property
    def stats(self) -> Mapping[str, PlcStats]: ...

    @property
    def dropped(self) -> int: ...

    def client(self, plc: str) -> Client:
        """The client of one PLC (how an element of an array tag is addressed)."""
        ...

    async def write(self, plc: str, address: str, values: Sequence[int] | Sequence[bool]) -> None:
        """A write of points through the PLC's one connection, never retried."""
        ...

    async def write_tag(self, plc: str, tag: str, value: object) -> None:
        """A write of a configured tag through the PLC's one connection, never retried."""
        ...


class ScanSource(PollerView, Protocol):
    """A poller as the runtime drives it: started, its scans consumed, closed."""

    async def start(self) -> None: ...

    async def aclose(self) -> None: ...

    def scans(self, wait: float = 0.0) -> AsyncIterator[list[Scan]]: ...

    def drain(self) -> list[Scan]: ...


@dataclass(frozen=True)
class PlcUpdate:
    """The PLCs a reload changed, by name, as each face learns them: after the poller applied
    them, so ``view`` (the run's poller view) shows the new configuration and tags.
    ``changed``: a PLC whose URL, tags or scan groups changed (its tags may differ now);
    every PLC not named keeps what it has."""

    view: PollerView
    added: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()
    changed: tuple[str, ...] = ()

    @property
    def empty(self) -> bool:
        return not (self.added or self.removed or self.changed)


class Face(Protocol):
    """What every face and sink of the north side implements; see the module docstring."""

    @property
    def name(self) -> str:
        """How logs, metrics and ``/healthz`` name it (``mqtt``, ``opcua``, ``web console``)."""
        ...

    async def start(self) -> None: ...

    async def aclose(self) -> None: ...

    def submit(self, scans: Sequence[Scan]) -> None: ...

    def probe(self, sample: Sample) -> None: ...

    async def update_plcs(self, update: PlcUpdate) -> None: ...

    def health(self) -> Health: ...

    def summary(self) -> str | None: ...

    def announce(self) -> str | None: ...

    def metrics(self) -> Iterator[Metric]: ...


class FaceBase:
    """Defaults of :class:`Face` for a face that needs none of them: nothing to start or
    stop, every sample taken, always healthy, nothing to say. A subclass sets ``name`` and
    writes ``submit``."""

    name = "face"

    async def start(self) -> None:
        """Nothing to start."""

    async def aclose(self) -> None:
        """Nothing to stop."""

    def submit(self, scans: Sequence[Scan]) -> None:
        raise NotImplementedError

    def probe(self, sample: Sample) -> None:
        """Every sample is taken."""

    async def update_plcs(self, update: PlcUpdate) -> None:
        """Nothing kept per PLC: the next scans say the rest."""

    def health(self) -> Health:
        return Health(self.name)

    def summary(self) -> str | None:
        return None

    def announce(self) -> str | None:
        return None

    def metrics(self) -> Iterator[Metric]:
        return iter(())
