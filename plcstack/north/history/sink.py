""":class:`History`: the embedded history as a north-side sink, and its queries.

On the event loop, :meth:`History.submit` only queues the scans (a list append; bounded at
:data:`QUEUE_LIMIT` samples: beyond, new samples are dropped, counted and said once per burst,
and the poller is never held up). Every :data:`COMMIT_EVERY` seconds a supervised task hands
the queue to the writer's own thread (:mod:`.writer`), which encodes and commits it; a task
that fails is restarted by the run's supervisor and named in ``/healthz`` meanwhile.
Queries (:meth:`History.query`) run in a second thread with their own connection, so a long
range being read never delays the writing.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

from plcstack.errors import ConfigError
from plcstack.north.face import FaceBase
from plcstack.north.health import Health
from plcstack.north.history.blocks import BlockError, decode_block
from plcstack.north.history.downsample import Downsampler
from plcstack.north.history.settings import HistorySettings
from plcstack.north.history.store import Damaged, HistoryFile
from plcstack.north.history.writer import Writer
from plcstack.north.supervise import Supervised, Supervisor
from plcstack.poll.samples import Scan
from plcstack.values import TagValue

if TYPE_CHECKING:
    from prometheus_client.core import Metric

__all__ = ["COMMIT_EVERY", "MAX_QUERIES", "QUEUE_LIMIT", "History", "HistoryBusy"]

log = logging.getLogger("plcstack.history")

#: seconds between two commits of the writer (what a killed process can lose)
COMMIT_EVERY = 1.0
#: samples waiting for the writer at most (20 s of 10,000 tags a second changing)
QUEUE_LIMIT = 200_000
#: queries running or waiting at once; more are refused (the reader is one thread)
MAX_QUERIES = 8


class HistoryBusy(Exception):
    """Too many queries at once, or the history is not open (yet, or any more)."""


class History(FaceBase):
    """The embedded history of one run (see the module's docstring); a face of the runtime."""

    #: how logs, metrics and ``/healthz`` name it
    name = "history"

    def __init__(
        self,
        settings: HistorySettings,
        *,
        supervisor: Supervisor | None = None,
        clock: Callable[[], float] = time.time,
        commit_every: float = COMMIT_EVERY,
        queue_limit: int = QUEUE_LIMIT,
        writer: Writer | None = None,
    ) -> None:
        self.settings = settings
        self.supervisor = supervisor
        self.clock = clock
        self.commit_every = commit_every
        self.queue_limit = queue_limit
        self.writer = writer or Writer(settings, clock=clock)
        #: samples dropped because the writer was :data:`QUEUE_LIMIT` behind, or because they
        #: came after :meth:`aclose` began (``late``)
        self.dropped = 0
        self.late = 0
        self._closed = False
        self._pending: list[Sequence[Scan]] = []
        self._held = 0
        self._dropping = 0
        self._queries = 0
        self._task: Supervised | None = None
        self._write_pool: ThreadPoolExecutor | None = None
        self._read_pool: ThreadPoolExecutor | None = None
        self._reader: HistoryFile | None = None
        self._open = False
        #: queries answered, and the seconds they took in all (``/metrics``)
        self.queries = 0
        self.query_seconds = 0.0
        #: queries refused (too many at once, not open, the file unreadable)
        self.query_refusals = 0

    # -- the sink protocol ----------------------------------------------------------------------
    def submit(self, scans: Sequence[Scan]) -> None:
        n = 0
        for scan in scans:
            n += len(scan.samples)
        if self._closed:  # a reload closes this history and opens another: these fall between
            if not self.late:
                log.warning(
                    "history: samples arrive while %s closes (a reload restarts the history):"
                    " they are not recorded until it is open again; counted as dropped",
                    self.settings.path,
                )
            self.late += n
            self.dropped += n
            return
        if self._held + n > self.queue_limit:
            if not self._dropping:
                log.warning(
                    "history: %d samples wait for the writer of %s (the disk is too slow?);"
                    " new samples are dropped until it catches up",
                    self._held,
                    self.settings.path,
                )
            self._dropping += n
            self.dropped += n
            return
        self._pending.append(scans)
        self._held += n

    async def start(self) -> None:
        """Open the file (a :class:`ConfigError` if it cannot be used) and start writing."""
        self._write_pool = ThreadPoolExecutor(1, thread_name_prefix="plcstack-history-write")
        self._read_pool = ThreadPoolExecutor(1, thread_name_prefix="plcstack-history-read")
        loop = asyncio.get_running_loop()
        try:
            await loop.run_in_executor(self._write_pool, self.writer.open)
        except BaseException:
            self._shutdown_pools()
            raise
        self._open = True
        if self.supervisor is None:
            self.supervisor = Supervisor()
        self._task = self.supervisor.start(self.name, self._run)

    async def aclose(self) -> None:
        """Write what is queued, checkpoint, close the file. Samples submitted from now on
        are counted as dropped (said once): a reload that restarts the history hands the
        next ones to the history it opens."""
        self._closed = True
        if self._task is not None:
            await self._task.stop()
            self._task = None
        if self._write_pool is None:
            return
        self._open = False
        loop = asyncio.get_running_loop()
        batches = self._take()
        try:
            await loop.run_in_executor(self._write_pool, self._close_writer, batches)
        finally:
            if self._reader is not None and self._read_pool is not None:
                await loop.run_in_executor(self._read_pool, self._reader.close)
                self._reader = None
            self._shutdown_pools()

    def _close_writer(self, batches: list[Sequence[Scan]]) -> None:
        try:
            self.writer.write(batches)
        finally:
            self.writer.close()

    def _shutdown_pools(self) -> None:
        for pool in (self._write_pool, self._read_pool):
            if pool is not None:
                pool.shutdown(wait=True)
        self._write_pool = self._read_pool = None

    def summary(self) -> str:
        stats = self.writer.stats
        return (
            f"history: {stats.taken} samples taken, {stats.stored} points written to"
            f" {self.settings.path}, {self.dropped + stats.dropped} dropped"
        )

    def health(self) -> Health:
        """Unhealthy while its commits fail (a full disk, an I/O error): why, since when, and
        the points that wait in memory meanwhile."""
        writer = self.writer
        figures = (("points waiting in memory", writer.open_points),)
        failure = writer.failure
        if failure is None:
            return Health(self.name, figures=figures)
        reason, since = failure
        return Health(self.name, f"cannot write to {writer.path} ({reason})", since, figures)

    def disk_bytes(self) -> int:
        """Bytes the history takes on disk: its file and the file's write-ahead log."""
        total = 0
        for suffix in ("", "-wal", "-shm"):
            with contextlib.suppress(OSError):
                total += os.stat(f"{self.writer.path}{suffix}").st_size
        return total

    def metrics(self) -> Iterator[Metric]:
        """The history's figures for ``/metrics`` (prometheus-client metric families)."""
        from prometheus_client.core import (
            CounterMetricFamily,
            GaugeMetricFamily,
            SummaryMetricFamily,
        )

        stats = self.writer.stats
        counters = (
            ("points_taken", "samples taken into the history (committed within a second)",
             stats.taken),
            ("points_stored", "points written into blocks by checkpoints", stats.stored),
            ("dropped_points", "samples dropped: the writer fell behind or the points waiting"
             " for a failing disk reached their bound", self.dropped + stats.dropped),
            ("write_errors", "commits that failed (disk full, I/O error); their points waited"
             " in memory", stats.failures),
            ("expired_points", "points deleted by retention", stats.expired),
            ("trimmed_points", "points deleted by max_size, oldest first", stats.trimmed),
            ("query_refusals", "queries refused: too many at once, or the history not open",
             self.query_refusals),
        )  # fmt: skip
        for name, doc, value in counters:
            yield CounterMetricFamily(f"plcstack_history_{name}", doc, value=float(value))
        yield SummaryMetricFamily(
            "plcstack_history_query_seconds",
            "history queries answered, and the seconds they took",
            count_value=self.queries,
            sum_value=self.query_seconds,
        )
        yield GaugeMetricFamily(
            "plcstack_history_disk_bytes",
            "bytes the history takes on disk (its file and write-ahead log)",
            value=float(self.disk_bytes()),
        )
        yield GaugeMetricFamily(
            "plcstack_history_write_lag_seconds",
            "from the arrival of the oldest sample of the last commit to that commit",
            value=stats.lag,
        )
        oldest = GaugeMetricFamily(
            "plcstack_history_oldest_point_age_seconds",
            "age of the oldest point the history holds (none while it holds none)",
        )
        if self.writer.oldest_ms is not None:
            oldest.add_metric([], max(0.0, self.clock() - self.writer.oldest_ms / 1000.0))
        yield oldest

    # -- writing --------------------------------------------------------------------------------
    def _take(self) -> list[Sequence[Scan]]:
        batches, self._pending, self._held = self._pending, [], 0
        if self._dropping:
            log.warning("history: writing again after dropping %d samples", self._dropping)
            self._dropping = 0
        return batches

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        assert self._write_pool is not None
        while True:
            await asyncio.sleep(self.commit_every)
            await loop.run_in_executor(self._write_pool, self.writer.write, self._take())

    async def flush(self) -> None:
        """Commit what is queued now (tests, and a query that must see the latest)."""
        if self._write_pool is None:
            return
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._write_pool, self.writer.write, self._take())

    # -- queries --------------------------------------------------------------------------------
    async def query(
        self, plc: str, tag: str, start: float, end: float, points: int = 1000
    ) -> list[tuple[float, TagValue | None]]:
        """The points of one tag from ``start`` to ``end`` (Unix seconds), at most ``points``
        (min and max per bucket beyond that), oldest first; the first may be older than
        ``start``: the value that held then. A bad-quality point's value is None."""
        if not self._open or self._read_pool is None:
            self.query_refusals += 1
            raise HistoryBusy("the history is not open")
        if self._queries >= MAX_QUERIES:
            self.query_refusals += 1
            raise HistoryBusy(f"{MAX_QUERIES} history queries are already running")
        self._queries += 1
        began = time.perf_counter()
        try:
            loop = asyncio.get_running_loop()
            found = await loop.run_in_executor(
                self._read_pool, self._query, (plc, tag), start, end, points
            )
        except HistoryBusy:
            self.query_refusals += 1
            raise
        finally:
            self._queries -= 1
        self.queries += 1
        self.query_seconds += time.perf_counter() - began
        return found

    def _query(
        self, key: tuple[str, str], start: float, end: float, limit: int
    ) -> list[tuple[float, Any]]:
        """In the reader thread."""
        if self._reader is None:
            try:
                self._reader = HistoryFile(self.writer.path, reader=True)
            except (Damaged, ConfigError) as exc:
                raise HistoryBusy(f"the history cannot be read: {exc}") from None
        reader = self._reader
        start_ms, end_ms = int(start * 1000.0), int(end * 1000.0)
        sampler = Downsampler(start_ms, end_ms, limit)
        writer = self.writer
        with writer.lock:  # the open points and the file as of one moment
            block = writer.blocks.get(key)
            open_block = None if block is None or not len(block) else block.copy()
            sid = -1 if block is None else block.sid
            reader.begin_read()
        try:
            if sid < 0:
                sid = reader.series().get(key, -1)
            before: tuple[int, Any] | None = None
            rows = reader.blocks(sid, start_ms, end_ms) if sid >= 0 else []
            for t0, data in rows:
                try:
                    times, values = decode_block(t0, data)
                except BlockError as exc:
                    log.warning("history: a block of %s/%s is damaged: %s", *key, exc)
                    continue
                before = _feed(sampler, times, values, before)
            if open_block is not None:
                before = _feed(sampler, *open_block.points(), before)
            if before is None and sid >= 0:
                row = reader.block_before(sid, start_ms)
                if row is not None:
                    try:
                        times, values = decode_block(*row)
                        before = (times[-1], values[-1])
                    except BlockError as exc:
                        log.warning("history: a block of %s/%s is damaged: %s", *key, exc)
        finally:
            reader.end_read()
        sampler.before = before
        return [(t / 1000.0, v) for t, v in sampler.result()]


def _feed(
    sampler: Downsampler, times: list[int], values: list[Any], before: tuple[int, Any] | None
) -> tuple[int, Any] | None:
    """One block's points into the sampler; the newest point before the range so far."""
    i = bisect.bisect_left(times, sampler.start)
    j = bisect.bisect_right(times, sampler.end, i)
    if i > 0 and (before is None or times[i - 1] >= before[0]):
        before = (times[i - 1], values[i - 1])
    sampler.add(times[i:j], values[i:j])
    return before
