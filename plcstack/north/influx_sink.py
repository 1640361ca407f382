"""The Influx writer: the lines of ``--format influx`` posted to InfluxDB 1.x, with no pipe.

Every line goes through a :class:`~plcstack.north.buffer.StoreAndForward` queue, the one the MQTT
sink uses (memory, then the SQLite file of ``[influx] buffer_path``, within ``buffer_max``), so
there is one path and one order whether InfluxDB is up or not. One task takes the oldest lines,
at most ``batch_size`` of them, once that many wait or the oldest has waited ``batch_wait``, and
posts them to ``URL/write?db=DATABASE&precision=ns``; only an answer removes them from the queue.
After an outage the lines held meanwhile go first, in order. A line carries its scan's
timestamp, so a batch posted twice (an answer lost with its connection) stores every point once:
InfluxDB keeps one point per measurement, tags and time.

InfluxDB's answers, told apart:

* ``204``: written.
* ``400`` (a line InfluxDB cannot store: a field whose type changed, a value it cannot parse):
  InfluxDB stores the other lines of the batch and refuses the request. The batch is halved and
  each half posted again until the refused lines stand alone; each is dropped, counted
  (``rejected``) and named in a WARNING with InfluxDB's reason (the next one with the same reason
  at DEBUG). The others go on. ``413`` (a batch over InfluxDB's ``max-body-size``) is halved the
  same way.
* ``401``/``403``: the credentials are wrong. No retry could fix them, and retries could lock
  the account: the writer stops sending, says so in one ERROR, and ``/healthz`` names it; lines
  keep being queued (within ``buffer_max``, on disk with ``buffer_path``) for a run with the
  right credentials.
* ``404`` (the database does not exist), ``5xx``, a refused or dropped connection, a timeout:
  retried with jittered backoff up to ``reconnect_max``; one WARNING when it begins, one when
  writes work again.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import logging
import ssl
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

from plcstack.north.buffer import Message, StoreAndForward, forwarding_health
from plcstack.north.face import FaceBase, PlcUpdate
from plcstack.north.health import Condition, Health
from plcstack.north.influx import InfluxFormat
from plcstack.north.influx_config import InfluxSettings
from plcstack.north.supervise import Supervised, Supervisor
from plcstack.poll.config import PlcConfig
from plcstack.poll.samples import Sample, Scan
from plcstack.transports.backoff import Backoff

if TYPE_CHECKING:
    from prometheus_client.core import Metric

__all__ = ["InfluxSink", "InfluxStats", "Outcome", "classify"]

log = logging.getLogger("plcstack.north.influx")

#: characters of a refused line shown in the log
SHOWN = 200


@dataclass
class InfluxStats:
    """Counters of the writer (lines, not requests)."""

    submitted: int = 0  # lines handed to the queue
    written: int = 0  # lines InfluxDB answered 204 for
    held: int = 0  # lines that waited while InfluxDB could not be written to
    replayed: int = 0  # of ``written``: lines that had been held
    rejected: int = 0  # lines InfluxDB refused (400), dropped
    late: int = 0  # lines of scans handed over after the writer closed (a reload restarting it)
    requests: int = 0  # POSTs answered (any status)
    failures: int = 0  # POSTs that failed (no answer, 5xx, 404) and were retried


@dataclass(frozen=True)
class Outcome:
    """What one answer of ``/write`` means for its batch: ``written``; ``split`` (halve it, a
    line alone is dropped); ``retry`` (the same batch after a backoff); ``stop`` (no retry can
    help). ``reason`` says why in words."""

    kind: str
    reason: str = ""


def classify(status: int, body: str) -> Outcome:
    """The outcome of one ``/write`` answer (``body``: InfluxDB's text, its JSON ``error``)."""
    detail = _error_text(body)
    if status == 204 or 200 <= status < 300:
        return Outcome("written")
    if status == 400:
        return Outcome("split", detail or "bad request")
    if status == 413:
        return Outcome("split", detail or "the request is larger than InfluxDB takes")
    if status in (401, 403):
        return Outcome("stop", f"{status}: {detail or 'authorization failed'}")
    if status == 404:
        return Outcome("retry", f"404: {detail or 'not found'} (CREATE DATABASE it?)")
    return Outcome("retry", f"{status}: {detail or 'no reason given'}")


def _error_text(body: str) -> str:
    import json

    text = body.strip()
    try:
        parsed = json.loads(text)
    except ValueError:
        return " ".join(text.split())[:500]
    if isinstance(parsed, dict) and isinstance(parsed.get("error"), str):
        return " ".join(parsed["error"].split())
    return " ".join(text.split())[:500]


class InfluxSink(FaceBase):
    """Writes the scans it is given to InfluxDB 1.x (``[influx] url``); see the module."""

    name = "influx"

    def __init__(
        self,
        settings: InfluxSettings,
        plcs: Iterable[PlcConfig],
        *,
        supervisor: Supervisor | None = None,
        buffer: StoreAndForward | None = None,
        env: Mapping[str, str] | None = None,
    ) -> None:
        if settings.url is None:
            raise ValueError("an Influx writer needs [influx] url")
        self.settings = settings
        self.format = InfluxFormat(plcs, layout=settings.layout, measurement=settings.measurement)
        self.buffer = buffer if buffer is not None else StoreAndForward.configured(settings)
        self.stats = InfluxStats()
        self.supervisor = supervisor if supervisor is not None else Supervisor()
        self.env = env
        #: InfluxDB took the last request (False before the first and while it fails)
        self.connected = False
        #: why writing does not work now (no problem while it does), and since when
        self.link = Condition(self.name)
        #: the credentials were refused: nothing is sent any more in this run
        self.stopped = False
        self._headers = {"Content-Type": "text/plain; charset=utf-8"}
        self._ssl: ssl.SSLContext | None = None
        self._session: Any = None
        self._task: Supervised | None = None
        self._wake = asyncio.Event()
        self._full = asyncio.Event()
        self._closing = False
        #: the queue is closed: nothing more can be queued by this writer
        self._closed = False
        self._idle = asyncio.Event()
        self._idle.set()
        #: every line up to this ``seq`` was counted in ``held`` (-1: none)
        self._held_through = -1
        self._last_rejection = ""
        self._backoff = Backoff(
            initial=min(0.5, settings.reconnect_max), maximum=settings.reconnect_max
        )

    @property
    def url(self) -> str:
        return str(self.settings.url)

    @property
    def _where(self) -> str:
        parts = urlsplit(self.url)
        port = parts.port or (443 if parts.scheme == "https" else 80)
        return f"{parts.hostname}:{port}"

    # -- in: scans ----------------------------------------------------------------------------
    def lines(self, scans: Sequence[Scan]) -> list[str]:
        """The line protocol of ``scans``, one string per line (no newline)."""
        if self.format.layout == "fields":
            return self.format.lines(scans)
        return self.format.text(scans).splitlines()

    async def update_plcs(self, update: PlcUpdate) -> None:
        """The lines of the PLCs of a reloaded configuration (a float32 tag added is written
        at float32 precision)."""
        settings = self.settings
        self.format = InfluxFormat(
            update.view.config.plcs, layout=settings.layout, measurement=settings.measurement
        )

    def submit(self, scans: Sequence[Scan]) -> None:
        """Queue the lines of these scans (never blocks, never raises for the network): all
        are encoded before the first is queued."""
        lines = self.lines(scans)
        if not lines:
            return
        if self._closed:  # a reload closed this writer and starts another: these fall between
            if not self.stats.late:
                log.warning(
                    "%s: lines arrive after the writer closed (a reload restarts it): they are"
                    " not written; counted",
                    self.name,
                    extra={"face": self.name},
                )
            self.stats.late += len(lines)
            return
        topic = self.settings.database
        put = self.buffer.put
        for line in lines:
            put(topic, line.encode())
        n = len(lines)
        self.stats.submitted += n
        if self.link.problem is not None:  # InfluxDB cannot be written to: these wait
            self._hold()
        self._idle.clear()
        self._wake.set()
        if len(self.buffer) >= self.settings.batch_size:
            self._full.set()

    def probe(self, sample: Sample) -> None:
        """Raise if ``sample`` cannot be written as a line; queues nothing."""
        self.lines([Scan(sample.plc, "probe", sample.source_time, sample.receive_time, (sample,))])

    # -- life cycle ---------------------------------------------------------------------------
    def prepare(self) -> None:
        """The credentials from the environment and the TLS context, once; a
        :class:`ConfigError` for what no retry can fix (a variable not set, a CA file that
        cannot be read), so the run does not start instead of failing for ever."""
        credentials = self.settings.credentials(self.env)
        if credentials is not None:  # HTTP basic authentication, as InfluxDB 1.x takes it
            token = base64.b64encode(":".join(credentials).encode()).decode()
            self._headers["Authorization"] = f"Basic {token}"
        if self.url.startswith("https:"):
            from plcstack.errors import ConfigError

            try:
                self._ssl = ssl.create_default_context(cafile=self.settings.ca_file)
            except OSError as exc:  # ssl.SSLError is an OSError
                raise ConfigError(
                    f"[influx] ca_file {self.settings.ca_file}: cannot be used:"
                    f" {exc.strerror or exc}"
                ) from None

    async def start(self) -> None:
        self.prepare()
        self._task = self.supervisor.start(self.name, self.run)

    async def aclose(self, *, drain: float = 2.0) -> None:
        """Write what can be written within ``drain`` s, then stop; what is left stays in the
        queue (on disk with ``buffer_path``, for the next run)."""
        self._closing = True
        self._full.set()  # a batch waiting for more lines goes now
        if self._task is not None and self.link.problem is None and drain > 0:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(drain):
                    await self._idle.wait()
        if self._task is not None:
            await self._task.stop()
            self._task = None
        if self._session is not None:
            await self._session.close()
            self._session = None
        self.buffer.close()  # what waits goes to disk (buffer_path): the next writer sends it
        self._closed = True
        waiting = len(self.buffer)
        if waiting and self.settings.buffer_path is None:
            log.warning(
                "%s: %d lines not written are lost as the writer closes ([influx] buffer_path"
                " would keep them for the next writer)",
                self.name,
                waiting,
                extra={"face": self.name},
            )

    async def wait_drained(self, timeout: float) -> None:
        """Wait until everything queued so far was written (``TimeoutError`` after it)."""
        async with asyncio.timeout(timeout):
            while len(self.buffer):
                self._idle.clear()
                await self._idle.wait()

    def summary(self) -> str:
        """One line for stderr at the end of a run: what was written, held and replayed,
        refused, and what is left where."""
        s, buffer = self.stats, self.buffer
        waiting = len(buffer)
        where = ""
        if waiting:
            path = self.settings.buffer_path
            where = f" (kept in {path} for the next run)" if path else " (lost: no buffer_path)"
        dropped = f"{buffer.dropped} dropped by buffer_max"
        if buffer.lost_to_disk:
            dropped += f" ({buffer.lost_to_disk} of them because the disk refused them)"
        return (
            f"{self.name} {self.url} database {self.settings.database}: {s.written} lines"
            f" written, {s.held} held while InfluxDB could not be written to and {s.replayed}"
            f" of them replayed, {s.rejected} rejected by InfluxDB, {waiting} not delivered"
            f"{where}, {dropped}"
        )

    # -- out: batches -------------------------------------------------------------------------
    async def run(self) -> None:
        """Post batches until cancelled (the supervisor restarts it if it dies)."""
        import aiohttp

        settings = self.settings
        if self._session is None:
            timeout = aiohttp.ClientTimeout(total=settings.timeout)
            connector = aiohttp.TCPConnector(limit=1, ssl=self._ssl if self._ssl else True)
            self._session = aiohttp.ClientSession(timeout=timeout, connector=connector)
        while True:
            if self.stopped:
                await asyncio.Event().wait()  # nothing more is sent in this run
            if not len(self.buffer):
                self._idle.set()
                self._wake.clear()
                await self._wake.wait()
                continue
            waits = settings.batch_wait > 0 and not self._closing  # closing: it goes as it is
            if len(self.buffer) < settings.batch_size and waits:
                self._full.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(settings.batch_wait):
                        await self._full.wait()
            batch = self.buffer.peek(settings.batch_size)
            if await self._post_all(batch):
                self._backoff.reset()
            else:
                await asyncio.sleep(self._backoff.next_delay())

    async def _post_all(self, batch: list[Message]) -> bool:
        """Post ``batch`` (halving it on 400/413); whether it is done (written or dropped).
        False: retry it after a backoff (or the writer stopped)."""
        self.buffer.in_flight_through = batch[-1].seq
        try:
            pending = [batch]
            while pending:
                part = pending.pop()
                outcome = await self._post(part)
                if outcome.kind == "written":
                    self._written(part)
                elif outcome.kind == "split" and len(part) > 1:
                    half = len(part) // 2
                    pending += [part[half:], part[:half]]  # the older half first
                elif outcome.kind == "split":
                    self._rejected(part[0], outcome.reason)
                elif outcome.kind == "stop":
                    self._stop(outcome.reason)
                    return False
                else:
                    self._failed(outcome.reason)
                    return False
            return True
        finally:
            self.buffer.in_flight_through = -1

    async def _post(self, part: list[Message]) -> Outcome:
        """One POST of ``part``; a failure without an answer is a ``retry``."""
        import aiohttp

        body = b"\n".join(m.payload for m in part)
        try:
            async with self._session.post(
                self.settings.write_url, data=body, headers=self._headers
            ) as response:
                text = await response.text(errors="replace")
                status = response.status
        except (aiohttp.ClientError, TimeoutError, OSError) as exc:
            return Outcome("retry", _no_answer(exc, self.settings.timeout, self._where))
        self.stats.requests += 1
        return classify(status, text)

    def _written(self, part: list[Message]) -> None:
        last = part[-1].seq
        self.buffer.ack(last)
        n = len(part)
        self.stats.written += n
        if part[0].seq <= self._held_through:
            self.stats.replayed += sum(1 for m in part if m.seq <= self._held_through)
        if not self.connected:
            self.connected = True
            if self.link.clear():
                log.warning(
                    "%s: InfluxDB at %s takes writes again; %d lines waiting are written first",
                    self.name,
                    self.url,
                    len(self.buffer),
                    extra={"face": self.name},
                )
        if not len(self.buffer):
            self._idle.set()

    def _rejected(self, message: Message, reason: str) -> None:
        self.buffer.ack(message.seq)
        self.stats.rejected += 1
        line = message.payload.decode(errors="replace")
        shown = line if len(line) <= SHOWN else line[:SHOWN] + f"... ({len(line)} characters)"
        kind = reason.replace(line, "LINE")
        level = logging.DEBUG if kind == self._last_rejection else logging.WARNING
        self._last_rejection = kind
        log.log(
            level,
            "%s: InfluxDB at %s refused a line, dropped (%d so far): %s; the line: %s",
            self.name,
            self.url,
            self.stats.rejected,
            reason,
            shown,
            extra={"face": self.name},
        )

    def _hold(self) -> None:
        """Count every line queued so far and not yet counted as held: each waits for an
        InfluxDB that cannot be written to (the queue's ``seq`` grows by one a line)."""
        last = self.buffer.next_seq - 1
        if last > self._held_through:
            self.stats.held += last - max(self._held_through, self._oldest_waiting() - 1)
            self._held_through = last

    def _oldest_waiting(self) -> int:
        waiting = self.buffer.peek(1)
        return waiting[0].seq if waiting else self.buffer.next_seq

    def _note(self, problem: str) -> bool:
        """Note why writes fail; True if that is news (then it is logged)."""
        self.connected = False
        self._hold()
        return self.link.fail(problem)

    def _failed(self, reason: str) -> None:
        self.stats.failures += 1
        problem = f"InfluxDB at {self.url} cannot be written to: {reason}"
        if self._note(problem):
            log.warning(
                "%s: %s; retrying with backoff, %d lines waiting",
                self.name,
                problem,
                len(self.buffer),
                extra={"face": self.name},
            )

    def _stop(self, reason: str) -> None:
        self.stopped = True
        problem = (
            f"InfluxDB at {self.url} refused the credentials ({reason}): writing stopped until"
            " a restart with the right username_env/password_env"
        )
        if self._note(problem):
            log.error("%s: %s", self.name, problem, extra={"face": self.name})

    def health(self) -> Health:
        """Unhealthy while InfluxDB cannot be written to or the disk under ``buffer_path``
        refuses writes: since when, why, how many lines wait."""
        return forwarding_health(self.link, self.buffer, "lines")

    def metrics(self) -> Iterator[Metric]:
        """The writer's figures for ``/metrics`` (prometheus-client metric families)."""
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        s, buffer = self.stats, self.buffer
        counters = (
            ("written_lines", "lines InfluxDB stored (answered 204)", s.written),
            ("held_lines", "lines that waited while InfluxDB could not be written to", s.held),
            ("replayed_lines", "of the written lines, those that had been held", s.replayed),
            ("rejected_lines", "lines InfluxDB refused (400), dropped; the log names them",
             s.rejected),
            ("request_failures", "requests without a useful answer (no connection, 5xx, 404),"
             " retried", s.failures),
            ("dropped_lines", "lines lost: dropped by buffer_max, or refused by a full disk",
             buffer.dropped),
        )  # fmt: skip
        for name, doc, value in counters:
            yield CounterMetricFamily(f"plcstack_influx_{name}", doc, value=float(value))
        gauges = (
            ("up", "1 while InfluxDB takes writes", float(self.link.problem is None)),
            ("backlog_lines", "lines waiting to be written", float(len(buffer))),
            ("backlog_bytes", "bytes waiting to be written", float(buffer.backlog_bytes)),
        )
        for gauge, text, level in gauges:
            yield GaugeMetricFamily(f"plcstack_influx_{gauge}", text, value=level)


def _no_answer(exc: BaseException, timeout: float, where: str) -> str:
    """Why a request got no answer, in plain words."""
    import errno

    import aiohttp

    if isinstance(exc, TimeoutError):
        return f"no answer within {timeout:g} s (timeout)"
    if isinstance(exc, aiohttp.ClientConnectorError):
        if exc.os_error.errno == errno.ECONNREFUSED:
            return f"connection refused: nothing listens on {where} (InfluxDB not running?)"
        reason = exc.os_error.strerror or str(exc.os_error)
        return f"cannot connect to {where}: {reason}"
    if isinstance(exc, aiohttp.ServerDisconnectedError):
        return f"{where} closed the connection before it answered"
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
