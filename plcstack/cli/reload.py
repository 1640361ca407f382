"""The running configuration of one run, and the one path that changes it while it runs.

:class:`RuntimeControl` is the runtime's :class:`~plcstack.north.control.ConfigControl`: SIGHUP
(``systemctl reload``), the web console's ``POST /api/config/reload`` and ``POST /api/config``
all take :meth:`RuntimeControl.reload` or :meth:`RuntimeControl.replace`, one at a time:

1. read the file (or take the text), and load it with every check of a start; a file that does
   not load is one ERROR line with the same ``FILE:LINE`` errors as at start, an
   :class:`~plcstack.north.control.ApplyOutcome` with ``ok`` false, and nothing changes;
2. apply the command line over it again (``--web-port`` stays), and compute the difference
   (:func:`plcstack.config.diff`);
3. (``replace``) write the text in place of the file: a temporary file in the same directory,
   flushed to disk, renamed over it, the previous file kept as ``FILE.bak``;
4. apply: the poller first (added PLCs start, removed ones stop, a changed URL reconnects,
   changed tags are planned again on the open connection), then every face learns the PLCs
   added, removed and changed, and each face whose table changed restarts alone
   (:meth:`plcstack.north.pipeline.North.apply`); then the ``[[gateway]]`` faces;
5. one INFO line (``reload (SIGHUP): PLCs added: ...; removed: ...; changed: ...``), naming
   what waits for a restart (``[poll] concurrency``, ``[report]``) and every face that could
   not start, and one record in the write audit (``"kind": "config"``) when the run keeps one.

Under systemd the whole of it is between ``RELOADING=1`` and ``READY=1``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

from plcstack.config import Config, ConfigDiff, diff, read_config
from plcstack.errors import ConfigError, PlcError
from plcstack.gateway.faces import GatewayFaces
from plcstack.north.control import ApplyOutcome
from plcstack.north.face import PlcUpdate
from plcstack.north.faces import missing, needs_of
from plcstack.north.pipeline import North
from plcstack.poll.config import PollConfig
from plcstack.poll.diff import PlcChanges
from plcstack.poll.engine import Applied
from plcstack.statefiles import fsync_directory
from plcstack.systemd.service import ServiceNotifier
from plcstack.tomlfile import TomlFile

__all__ = ["Prepare", "ReconfigurablePoller", "Running", "RuntimeControl"]

log = logging.getLogger("plcstack.reload")

#: what a run makes of a loaded file before it runs it: the command line over it (``--web-port``),
#: the shard it polls; the same at start and at every reload
Prepare = Callable[[Config], Config]


class ReconfigurablePoller(Protocol):
    """The poller side of a reload (a :class:`~plcstack.poll.engine.Poller`, or a scale-out
    :class:`~plcstack.scale.worker.Worker`)."""

    @property
    def config(self) -> PollConfig: ...

    async def apply(self, changes: PlcChanges) -> Applied: ...


@dataclass(frozen=True)
class Running:
    """What a reload changes in a run: its poller, its north side, its ``[[gateway]]`` faces
    and what it tells systemd."""

    poller: ReconfigurablePoller
    north: North
    natives: GatewayFaces | None = None
    service: ServiceNotifier | None = None


def _same(config: Config) -> Config:
    return config


class RuntimeControl:
    """The running configuration of one run (see the module docstring). Made with
    :meth:`load` before the run's parts are built from :attr:`config`; :meth:`attach` hands it
    the running parts once they are built."""

    def __init__(self, path: str | Path, file: TomlFile, config: Config, prepare: Prepare) -> None:
        self._path = Path(path)
        self._file = file
        self._config = config
        self._prepare = prepare
        self._running: Running | None = None
        self._lock = asyncio.Lock()
        #: reloads applied and refused so far
        self.applied = 0
        self.refused = 0

    @classmethod
    def load(cls, path: str | Path, prepare: Prepare = _same) -> RuntimeControl:
        """Read and check the file at ``path`` as a start does (:class:`ConfigError` naming
        FILE:LINE); ``prepare`` is applied to it now and at every reload."""
        file = TomlFile.read(path)
        return cls(path, file, prepare(read_config(file)), prepare)

    @property
    def path(self) -> Path:
        return self._path

    @property
    def config(self) -> Config:
        """The configuration the run applies now (the command line over it)."""
        return self._config

    def text(self) -> str:
        return self._file.text

    def attach(self, running: Running) -> None:
        """The run's parts, built from :attr:`config` and started: what a reload changes."""
        self._running = running

    async def reload(self, *, who: str) -> ApplyOutcome:
        return await self._apply(lambda: TomlFile.read(self._path), who, write=False)

    async def replace(self, text: str, *, who: str) -> ApplyOutcome:
        return await self._apply(lambda: TomlFile.parse(text, str(self._path)), who, write=True)

    # -- the one path ---------------------------------------------------------------------------
    async def _apply(self, read: Callable[[], TomlFile], who: str, *, write: bool) -> ApplyOutcome:
        """One reload at a time, between ``RELOADING=1`` and ``READY=1`` under systemd."""
        async with self._lock:
            running = self._running
            service = running.service if running is not None else None
            if service is not None:
                service.reloading()
            try:
                outcome = await self._apply_locked(read, who, write, running)
            except BaseException as exc:  # READY=1 all the same: systemd waits for it
                if service is not None:
                    what = " ".join(str(exc).split())
                    service.reloaded(
                        status=f"reload failed part way: {type(exc).__name__}: {what}"
                        if what
                        else f"reload failed part way: {type(exc).__name__}"
                    )
                raise
            if service is not None:
                service.reloaded(None if outcome.ok else " ".join(outcome.errors))
            return outcome

    async def _apply_locked(
        self, read: Callable[[], TomlFile], who: str, write: bool, running: Running | None
    ) -> ApplyOutcome:
        try:
            file = read()
            new = self._prepare(read_config(file))
            problem = missing(needs_of(new.north))
            if problem is not None:
                raise ConfigError(problem)
        except (ConfigError, ValueError) as exc:
            return self._refuse(who, exc)
        if running is None:
            return self._refuse(who, ConfigError("the run is still starting; nothing changed"))
        changes = diff(self._config, new)
        previous = self._file.text
        if write:
            try:
                _write_atomically(self._path, file.text)
            except OSError as exc:
                text = f"cannot write {self._path}: {exc.strerror or exc}"
                return self._refuse(who, ConfigError(text))
        try:
            applied = await running.poller.apply(changes.plcs)
        except PlcError as exc:  # a change that cannot be planned: the poller is as it was
            if write:
                with contextlib.suppress(OSError):
                    _write_atomically(self._path, previous, backup=False)
            return self._refuse(who, exc)
        self._config, self._file = new, file
        line, failed = await self._apply_faces(running, new, changes, applied)
        self.applied += 1
        log.info("reload (%s): %s", who, line)
        self._audit(running, who, ok=True, summary=line)
        return ApplyOutcome(True, line, tuple(failed))

    async def _apply_faces(
        self, running: Running, new: Config, changes: ConfigDiff, applied: Applied
    ) -> tuple[str, list[str]]:
        """Every face's part of the reload; the INFO line and the faces that failed."""
        update = PlcUpdate(
            running.north.poller,
            added=applied.added,
            removed=tuple(applied.removed),
            changed=(*applied.reconnected, *applied.replanned),
        )
        tables = [t for t in changes.tables if t != "gateway"]
        faces = await running.north.apply(new.north, update, tables)
        waiting = [f"[poll] {key}" for key in applied.not_applied] + list(faces.not_applied)
        failed = list(faces.failed)
        natives, said = running.natives, ""
        if natives is not None:
            # after the poller: a PLC it connected anew gets its faces on the new connection
            native = await natives.apply(new.gateway)
            failed.extend(native.failed)
            if native.started or native.restarted or native.closed:  # failures: in failed
                said = f"; [[gateway]] {replace(native, failed=()).summary()}"
        elif "gateway" in changes.tables:
            waiting.append("[[gateway]]")
        return _line(update, faces.restarted, waiting, failed) + said, failed

    def _refuse(self, who: str, exc: Exception) -> ApplyOutcome:
        """A file that does not load: one ERROR line, the same errors as at start, nothing
        changed."""
        errors = tuple(str(exc).splitlines()) or (type(exc).__name__,)
        self.refused += 1
        log.error(
            "reload (%s): %s does not load, nothing changed: %s",
            who,
            self._path,
            " ".join(" ".join(errors).split()),
        )
        if self._running is not None:
            self._audit(self._running, who, ok=False, summary=errors[0])
        return ApplyOutcome(False, "nothing changed", errors)

    def _audit(self, running: Running, who: str, *, ok: bool, summary: str) -> None:
        audit = running.north.audit
        if audit is not None:
            audit.config_change(
                source=who, file=str(self._path), ok=ok, summary=summary, now=time.time()
            )


def _names(names: tuple[str, ...] | list[str], most: int = 10) -> str:
    if not names:
        return "none"
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


def _line(
    update: PlcUpdate, restarted: tuple[str, ...], waiting: list[str], failed: list[str]
) -> str:
    """``PLCs added: a; removed: b; changed: c`` and what else there is to say."""
    text = (
        f"PLCs added: {_names(update.added)}; removed: {_names(update.removed)};"
        f" changed: {_names(update.changed)}"
    )
    if restarted:
        text += f"; faces restarted: {', '.join(restarted)}"
    if waiting:
        text += f"; not applied (restart needed): {', '.join(waiting)}"
    if failed:
        text += f"; failed: {'; '.join(failed)}"
    return text


def _keep(path: Path, bak: Path) -> None:
    """``bak`` becomes the file at ``path`` as it is now (a second name of it, or a copy where
    the file system has no hard links), replacing an older ``bak`` at once; ``path`` is never
    missing meanwhile."""
    fd, tmp = tempfile.mkstemp(prefix=f".{bak.name}.", suffix=".tmp", dir=bak.parent)
    os.close(fd)
    try:
        os.unlink(tmp)
        try:
            os.link(path, tmp)
        except OSError:
            shutil.copy2(path, tmp)
        os.replace(tmp, bak)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _write_atomically(path: Path, text: str, *, backup: bool = True) -> None:
    """``text`` in place of the file at ``path``: a temporary file in the same directory,
    flushed to disk, renamed over it (a reader sees the old file or the new, never half of
    one); the previous file kept as ``FILE.bak`` (``backup``)."""
    directory = path.parent
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(FileNotFoundError):
            os.chmod(tmp, path.stat().st_mode & 0o7777)
        if backup and path.exists():
            _keep(path, path.with_name(path.name + ".bak"))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_directory(directory)
