"""The runtime's north side: one consumer of the poller's scans, report-by-exception once, then
every face of the run.

```python
config = load_config("plant.toml")
async with Poller(config.poll) as poller, North(poller, config.north) as north:
    await north.run()      # until cancelled: MQTT, OPC UA, Modbus, web, metrics as configured
```

:class:`North` builds, once per run, what every face shares: the supervisor, the write audit,
the one write path (:class:`~plcstack.north.writes.WritePath`), the report-by-exception filter
and the metrics collector; then each face the file configures (:mod:`plcstack.north.faces`),
handing it what it needs, plus the faces a caller passes in (the stdout formats of ``plcstack
poll``). Each face implements one protocol (:class:`~plcstack.north.face.Face`).

The consumer takes the poller's scans (:class:`~plcstack.poll.samples.Scan`: PLC, group,
times, samples) in batches that gather for ``[poll] batch_wait`` seconds after their first
scan (10 ms by default: with a thousand PLCs, one wake-up per event-loop pass cost more CPU
than the requests themselves), lets the metrics and the write audit see them (``up`` needs the
unfiltered truth), filters each scan once through :class:`ReportByException` and hands the same
list of scans to each face's ``submit``. Faces never block the consumer: a sink queues, a
server applies them to what its clients read. Writes come back the other way only through the
one write path and the poller's single-flight ``write_tag``.

Every face is supervised (:mod:`plcstack.north.supervise`): a sample a face cannot take costs
that sample only (ERROR log with PLC and tag, ``plcstack_sink_errors_total{sink}``), a task of a
face that dies is restarted with backoff; :meth:`North.health` says how every part of the run
is (``/healthz`` of the metrics endpoint and of the web console alike).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections import deque
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import TypeVar

from plcstack.errors import ConfigError, PlcError
from plcstack.north.audit import Audit
from plcstack.north.config import NorthConfig
from plcstack.north.control import ConfigControl
from plcstack.north.face import Face, PlcUpdate, ScanSource
from plcstack.north.faces import FACES, FaceContext, build_face, build_faces, restarts
from plcstack.north.health import Health
from plcstack.north.layout import Reachability, scan_groups
from plcstack.north.metrics import MetricsServer, PlcstackCollector
from plcstack.north.mqtt import MqttSink
from plcstack.north.rbe import ReportByException
from plcstack.north.supervise import Supervisor
from plcstack.north.writes import WritePath
from plcstack.poll.samples import Scan
from plcstack.resource import AsyncResource

__all__ = ["RUN_TABLES", "FacesApplied", "North"]

log = logging.getLogger("plcstack.north")

_F = TypeVar("_F")

#: scans held for one face while a reload restarts it (a restart takes a second or two; at
#: 1000 PLCs a second this is more than a minute of them)
HOLD_LIMIT = 100_000

#: north-side tables that belong to the whole run rather than to one face: a change of one of
#: them takes effect at the next start (a reload says so; it never ignores it silently)
RUN_TABLES = ("report", "audit")


@dataclass(frozen=True)
class FacesApplied:
    """What :meth:`North.apply` did to the faces."""

    #: the faces closed and started again from their changed tables (``[web]``, ``[mqtt]``)
    restarted: tuple[str, ...] = ()
    #: one line per face that could not take the change or start again (the others go on)
    failed: tuple[str, ...] = ()
    #: changed tables of the whole run, applied at the next start (``[report]``, ``[audit]``)
    not_applied: tuple[str, ...] = ()


@dataclass
class _Held:
    """The scans kept for one face while a reload restarts it (the newest ``HOLD_LIMIT``) and
    how many were reported meanwhile."""

    scans: deque[Scan] = field(default_factory=lambda: deque(maxlen=HOLD_LIMIT))
    total: int = 0


def _describe(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


async def _close(face: Face) -> None:
    """Close one face; a failure is said, never raised (the others still close)."""
    try:
        await face.aclose()
    except Exception as exc:
        log.error("%s: closing failed: %s", face.name, _describe(exc), extra={"face": face.name})


async def _started(face: Face | None) -> Face | None:
    """``face`` started (closed again if its start fails part way)."""
    if face is not None:
        try:
            await face.start()
        except BaseException:
            await _close(face)
            raise
    return face


class North(AsyncResource):
    """The north side of one run; see the module docstring. ``faces``: faces built by the
    caller, fed first (the stdout formats); the configured ones follow. ``supervisor``: the
    run's, when the caller's faces were built with it (default: a new one). ``control``: the
    running configuration, for the faces that show or change it (the web console)."""

    def __init__(
        self,
        poller: ScanSource,
        config: NorthConfig,
        *,
        faces: Sequence[Face] = (),
        supervisor: Supervisor | None = None,
        control: ConfigControl | None = None,
    ) -> None:
        self.poller = poller
        self.config = config
        self.rbe = ReportByException(config.report)
        self.supervisor = supervisor if supervisor is not None else Supervisor()
        self.audit: Audit | None = None
        if config.audit is not None:
            self.audit = Audit(config.audit, on_error=lambda: self.supervisor.count("audit"))
        #: the one write path of every face of this run
        self.writes = WritePath(poller, audit=self.audit)
        #: whether each PLC is reachable, by the rule the MQTT status uses: changes are logged
        self.reachability = Reachability(scan_groups(poller.config.plcs))
        self._offline: set[str] = set()
        #: the caller's faces, then the configured ones by the table of their kind
        self._callers: list[Face] = list(faces)
        self.faces: list[Face] = list(faces)
        self.collector = PlcstackCollector(
            poller, rbe=self.rbe, supervisor=self.supervisor, faces=lambda: self.faces
        )
        self._context = FaceContext(
            poller,
            config,
            self.writes,
            self.supervisor,
            self.collector,
            self.health,
            self.reachability.get,
            control=control,
        )
        self._configured = build_faces(self._context)
        self.faces.extend(self._configured.values())
        #: the faces a reload could not start again, by table: in :meth:`health` until one does
        self._down: dict[str, Health] = {}
        #: the scans reported while a reload restarts a face, by its table: handed to the face
        #: that starts again (the one closing takes no more), at most HOLD_LIMIT of them
        self._held: dict[str, _Held] = {}
        #: set once every PLC's first scan is in (a PLC that does not answer: once that scan
        #: failed): a client that connects to a face then reads values
        self.ready = asyncio.Event()
        self._waiting = {plc for plc in poller.plcs if poller.tags(plc)}
        if not self._waiting:
            self.ready.set()
        self._running = False

    # -- the faces ------------------------------------------------------------------------------
    def faces_of(self, kind: type[_F]) -> list[_F]:
        """The faces of the run of one class (``north.faces_of(WebConsole)``)."""
        return [face for face in self.faces if isinstance(face, kind)]

    def face(self, kind: type[_F]) -> _F | None:
        """The run's face of one class, None if it has none."""
        found = self.faces_of(kind)
        return found[0] if found else None

    @property
    def mqtt(self) -> MqttSink | None:
        return self.face(MqttSink)

    @property
    def metrics(self) -> MetricsServer | None:
        return self.face(MetricsServer)

    def health(self) -> list[Health]:
        """Every part of the run: the poller, each face, the audit, each supervised task that
        is down (see :mod:`plcstack.north.health`)."""
        parts = [Health("poller", None if self._running else "the poller is not running")]
        parts += [face.health() for face in self.faces]
        parts += self._down.values()
        if self.audit is not None:
            parts.append(self.audit.health())
        parts += self.supervisor.health()
        return parts

    def announcements(self) -> list[str]:
        """Where each face is found, as it says it (``OPC UA server listening on ...``)."""
        return [line for face in self.faces if (line := face.announce()) is not None]

    # -- life cycle -----------------------------------------------------------------------------
    async def aopen(self) -> None:
        """Open the audit and start every face, in order. A face that cannot start ends the
        start: what was started is stopped, and a :class:`ConfigError` names the face and why
        (a port taken, a certificate unreadable; the command's exit 2)."""
        try:
            if self.audit is not None:
                self.audit.open()  # a file that cannot be written stops the start (exit 2)
            for face in self.faces:
                try:
                    await face.start()
                except ConfigError:
                    raise  # says what and where already
                except Exception as exc:  # a PlcError says what; anything else is named
                    what = str(exc) if isinstance(exc, PlcError) else _describe(exc)
                    raise ConfigError(f"{face.name} cannot start: {what}") from exc
        except BaseException:
            await self.aclose()
            raise
        self._running = True

    async def aclose(self) -> None:
        self._running = False
        for face in self.faces:
            await _close(face)
        await self.supervisor.aclose()
        if self.audit is not None:
            self.audit.close()

    # -- reconfigured while it runs ------------------------------------------------------------
    async def apply(
        self, config: NorthConfig, update: PlcUpdate, tables: Collection[str] = ()
    ) -> FacesApplied:
        """A reload's part on the north side, after the poller applied the PLC changes: every
        face that goes on learns the PLCs added, removed and changed (``update``); each face
        whose table changed (``tables``, or one it is built with) is closed, built from
        ``config`` and started alone. A face that cannot take the change or start is one ERROR
        line and named in :meth:`health`; the others go on. ``[report]`` and ``[audit]`` are the
        whole run's and wait for the next start (:attr:`FacesApplied.not_applied`)."""
        removed = set(update.removed)
        if not update.empty:
            plcs = self.poller.config.plcs
            self.reachability.reconfigure(scan_groups(plcs), update.changed)
            self.rbe.forget(removed | set(update.changed))
            self.collector.forget(removed)
            self._offline -= removed
            self._waiting -= removed
        not_applied = tuple(f"[{t}]" for t in tables if t in RUN_TABLES)
        kinds = restarts([t for t in tables if t not in RUN_TABLES])
        again = {kind.table for kind in kinds}
        failed: list[str] = []
        if not update.empty:
            for face in self._callers + [f for t, f in self._configured.items() if t not in again]:
                try:
                    await face.update_plcs(update)
                except Exception as exc:  # that face is behind; the others go on
                    line = f"{face.name}: could not take the changed PLCs: {_describe(exc)}"
                    log.error("%s", line, extra={"face": face.name})
                    failed.append(line)
        # what a restarted face is built from; the run's own tables stay as they started
        self.config = dataclasses.replace(
            config, report=self.config.report, audit=self.config.audit
        )
        context = dataclasses.replace(self._context, config=self.config)
        restarted: list[str] = []
        for kind in kinds:
            old = self._configured.pop(kind.table, None)
            self._down.pop(kind.table, None)
            if old is not None:
                # from here the scans for this face wait for the one that starts again
                self._held[kind.table] = _Held()
                self.faces = [face for face in self.faces if face is not old]
                await _close(old)
            try:
                fresh = await _started(build_face(kind, context, self._configured))
            except Exception as exc:  # this face is down; the others go on
                what = str(exc) if isinstance(exc, PlcError) else _describe(exc)
                line = f"[{kind.table}] cannot start after the reload: {what}"
                held = self._held.pop(kind.table, None)
                if held is not None and held.total:
                    line += f"; {held.total} scans reported meanwhile are not delivered to it"
                log.error("%s; the other faces go on", line, extra={"face": kind.table})
                self._down[kind.table] = Health(f"[{kind.table}]", line)
                failed.append(line)
                continue
            held = self._held.pop(kind.table, None)
            if fresh is not None:  # None: its table is gone
                if held is not None:
                    self._hand_over(fresh, held)
                self.faces = [*self.faces, fresh]  # fed from now on, while others restart
                self._configured[kind.table] = fresh
                restarted.append(fresh.name)
        order = [kind.table for kind in FACES]
        self._configured = {t: self._configured[t] for t in order if t in self._configured}
        self.faces = self._callers + list(self._configured.values())
        return FacesApplied(tuple(restarted), tuple(failed), not_applied)

    def _hand_over(self, face: Face, held: _Held) -> None:
        """The scans reported while ``face`` restarted, to the face started again; a restart
        that outlasted :data:`HOLD_LIMIT` scans lost the oldest, counted and said once here."""
        lost = held.total - len(held.scans)
        if lost:
            self.supervisor.count(face.name, lost)
            log.warning(
                "%s: its restart outlasted %d scans: the %d oldest scans reported meanwhile"
                " are not delivered to it",
                face.name,
                HOLD_LIMIT,
                lost,
                extra={"face": face.name},
            )
        if held.scans:
            self.supervisor.submit(face.name, face.submit, list(held.scans), face.probe)

    def summary(self) -> list[str]:
        """One line per face for stderr at the end of a run: what it did (sent, not delivered
        and where it is kept, dropped), and the samples it could not take."""
        lines = []
        for face in self.faces:
            text = face.summary()
            errors = self.supervisor.errors.get(face.name, 0)
            if text is not None:
                lines.append(f"{text}, {errors} sink errors")
            elif errors:
                lines.append(f"{face.name}: {errors} sink errors (samples it could not take)")
        return lines

    # -- scans ----------------------------------------------------------------------------------
    def deliver(self, batch: Sequence[Scan]) -> list[Scan]:
        """One batch of scans through metrics, RBE and every face; returns what was reported."""
        self.collector.observe(batch)
        self.writes.observe(batch)  # the audit's "previous" (nothing without an audit)
        self._log_reachability(batch)
        reported = self.rbe.filter(batch) if self.config.reports_by_exception else list(batch)
        if reported:
            submit = self.supervisor.submit
            for face in self.faces:
                submit(face.name, face.submit, reported, face.probe)
            for held in self._held.values():  # a face a reload restarts: for the new one
                held.scans.extend(reported)
                held.total += len(reported)
        waiting = self._waiting
        if waiting:
            waiting.difference_update(scan.plc for scan in batch)
            if not waiting:
                self.ready.set()
        return reported

    def _log_reachability(self, batch: Sequence[Scan]) -> None:
        """A PLC going offline (with the reason) and coming back: one WARNING per change, so
        an operator sees it at the default log level, not once per scan."""
        update = self.reachability.update
        for scan in batch:
            state = update(scan)
            if state is None:
                continue
            plc = scan.plc
            if not state:
                reason = next((s.error for s in scan.samples if s.error), None) or "no good value"
                log.warning("PLC %s is offline: %s", plc, reason, extra={"plc": plc})
                self._offline.add(plc)
            elif plc in self._offline:
                self._offline.discard(plc)
                log.warning("PLC %s is back online", plc, extra={"plc": plc})
            else:
                log.info("PLC %s is online", plc, extra={"plc": plc})

    async def run(self) -> None:
        """Consume the poller's (or a scale-out Worker's) scans until cancelled: one list per
        wake-up, gathered for ``batch_wait``."""
        poller = self.poller
        async for batch in poller.scans(wait=poller.config.batch_wait):
            self.deliver(batch)
