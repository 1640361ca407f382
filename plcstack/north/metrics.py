"""``/metrics`` (Prometheus text format) and ``/healthz`` over a small asyncio HTTP server.

prometheus-client (the ``metrics`` extra) renders the text; the numbers come from the poller's
own counters at scrape time (a custom collector, so nothing is counted twice and the poll path
pays nothing per request), plus the latency histogram, which is fed once a second from each
PLC's latency window (only the latencies added since the last look, via ``LatencyWindow.tail``).

Failed requests get their own histogram, not a label on the successful one: a timeout lasts the
whole deadline and a refused connection microseconds, so mixing them into one distribution would
move the percentiles an operator alarms on for reasons that are not latency (the error counters
say how often requests fail; this says how long a failure keeps a scan waiting, per kind). The
poller keeps no latency for a failed request, so it is taken from the bad samples: each failed
request gives its tags bad samples with the request's send time (``source_time``) and the time
the failure was known (``receive_time``), and the error text naming the request; one observation
per distinct (PLC, send time, error). Samples that are bad although their request succeeded (a
value that does not decode: ``ValueDecodeError``) and the rest of a scan given up after a lost
connection (never sent: ``receive_time == source_time``) are not failed requests. Samples the
poller dropped for a slow consumer are not seen.

Exported (``plc`` label per PLC)::

    plcstack_plc_up                      1 if the PLC's latest sample was good, else 0
    plcstack_requests_total              requests sent
    plcstack_errors_total                failed requests and writes
    plcstack_reconnects_total            connections (re)established after the first
    plcstack_connect_failures_total
    plcstack_overruns_total              scans that ran past their next due time
    plcstack_samples_total / plcstack_bad_samples_total
    plcstack_writes_total
    plcstack_request_latency_seconds     histogram of successful requests (as the poll table)
    plcstack_failed_request_latency_seconds  histogram of failed requests, labels plc and error
                                         (the PlcError type): time until the failure was known
    plcstack_dropped_samples_total       (no label) samples dropped for a slow consumer
    plcstack_buffer_backlog_messages     store-and-forward backlog, per sink
    plcstack_buffer_backlog_bytes
    plcstack_buffer_dropped_messages_total  lost: dropped by the byte budget, or refused by the disk
    plcstack_mqtt_connected, plcstack_mqtt_sent_total, plcstack_mqtt_replayed_total,
    plcstack_mqtt_connection_failures_total
    plcstack_rbe_suppressed_total        samples held back by report-by-exception
    plcstack_sink_errors_total           per sink (``sink`` = its name): samples it could not
                                         take and deaths of its task (logged at ERROR)
    plcstack_face_guard_total            per listening face and reason: connections refused or
                                         closed to protect the other clients, malformed requests

``/healthz`` answers 200 only while every face and sink of the run is healthy (body ``ok`` and
a line per part), 503 otherwise, naming each part that is not, why and since when
(:mod:`plcstack.north.health`); ``/livez`` answers 200 ``alive`` while the process runs. The server
binds 127.0.0.1 unless ``[metrics] listen`` says otherwise: metrics name every PLC of the plant.
Requests are read with a size limit and a deadline (:data:`REQUEST_TIMEOUT` for the request and
its answer together); anything but ``GET`` of these two paths gets 404/405, never a crash. A
client that does not read its answer is dropped at that deadline (before, it held its
connection, its task and the whole answer for ever), and at most :data:`MAX_CLIENTS` are
served at once: a scrape takes milliseconds, so more at once is a flood, turned away.
"""

from __future__ import annotations

import asyncio
import bisect
import logging
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from plcstack.checks import Listen, Table
from plcstack.errors import ConfigError, ValueDecodeError
from plcstack.north.face import Face, FaceBase, PollerView
from plcstack.north.health import Health, healthz_body
from plcstack.north.mqtt import MqttSink
from plcstack.north.rbe import ReportByException
from plcstack.north.supervise import Supervised, Supervisor
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.resource import cancel_until_done
from plcstack.transports.guard import (
    LIMIT_KEYS,
    TOTALS,
    FaceGuard,
    Limits,
    close_writer,
    parse_limits,
)

if TYPE_CHECKING:
    from prometheus_client.core import Metric

__all__ = [
    "LATENCY_BUCKETS",
    "MAX_CLIENTS",
    "MetricsServer",
    "MetricsSettings",
    "PlcstackCollector",
    "parse_metrics",
]

#: histogram bucket bounds in seconds (PLC requests: a few ms on a LAN, up to the deadline)
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)
log = logging.getLogger("plcstack.north")

#: a request head larger than this is refused
MAX_REQUEST = 8192
#: seconds for reading a request and sending its answer; a client slower than that is dropped
REQUEST_TIMEOUT = 5.0
#: clients served at once (Prometheus and an operator's curl need a few)
MAX_CLIENTS = 16
#: failed requests remembered to count each once although all its tags carry it
SEEN_FAILURES = 4096


#: where ``/metrics`` and ``/healthz`` listen unless ``[metrics] listen`` says otherwise: loopback
#: only, since metrics name every PLC of the plant
DEFAULT_LISTEN = Listen("127.0.0.1", 9108)
#: clients at once (12 from one host), a request within REQUEST_TIMEOUT of connecting; no
#: idle timeout: a connection serves one request and is closed
DEFAULT_LIMITS = Limits(
    max_clients=MAX_CLIENTS, first_request_timeout=REQUEST_TIMEOUT, idle_timeout=None
)


@dataclass(frozen=True)
class MetricsSettings:
    host: str = DEFAULT_LISTEN.host
    port: int = DEFAULT_LISTEN.port
    #: clients at once and per host, the first request's deadline
    limits: Limits = DEFAULT_LIMITS

    @property
    def listen(self) -> Listen:
        return Listen(self.host, self.port)


def parse_metrics(table: object) -> MetricsSettings:
    """``[metrics]``: ``listen = "HOST:PORT"`` (default 127.0.0.1:9108; port 0 = any free
    port) and the client limits (``max_clients``, ``max_clients_per_host``,
    ``first_request_timeout``). The old ``host`` and ``port`` keys still load, with a notice."""
    t = Table.of(table, "metrics")
    t.keys(("listen", "host", "port", *LIMIT_KEYS[:3]))
    listen = t.listen(DEFAULT_LISTEN)
    return MetricsSettings(listen.host, listen.port, parse_limits(t, DEFAULT_LIMITS))


class _Histogram:
    __slots__ = ("counts", "seen", "sum")

    def __init__(self) -> None:
        self.counts = [0] * (len(LATENCY_BUCKETS) + 1)  # last: above the largest bound
        self.sum = 0.0
        self.seen = 0  # LatencyWindow.total at the last look

    def add(self, values: Iterable[float]) -> None:
        counts = self.counts
        for v in values:
            counts[bisect.bisect_left(LATENCY_BUCKETS, v)] += 1
            self.sum += v

    def buckets(self) -> list[tuple[str, float]]:
        out, running = [], 0
        for bound, count in zip(LATENCY_BUCKETS, self.counts, strict=False):
            running += count
            out.append((repr(bound), float(running)))
        out.append(("+Inf", float(running + self.counts[-1])))
        return out


class PlcstackCollector:
    """A prometheus-client collector over a poller, its MQTT sinks, the RBE filter and the
    faces of the run (each face's own :meth:`~plcstack.north.face.Face.metrics`)."""

    def __init__(
        self,
        poller: PollerView,
        sinks: Sequence[MqttSink] = (),
        rbe: ReportByException | None = None,
        supervisor: Supervisor | None = None,
        faces: Callable[[], Sequence[Face]] = lambda: (),
    ) -> None:
        """``supervisor``: the run's :class:`~plcstack.north.supervise.Supervisor`, whose
        ``errors`` (sink name -> failures) become ``plcstack_sink_errors_total``; ``faces``:
        the faces of the run when it is scraped (their MQTT sinks' queues and connections, and
        each face's own figures)."""
        self.poller = poller
        self.supervisor = supervisor
        self.sinks = list(sinks)
        self.rbe = rbe
        self.faces = faces
        self._up: dict[str, bool] = {}
        self._histograms: dict[str, _Histogram] = {}
        #: (plc, error type name) -> latencies of failed requests
        self._failures: dict[tuple[str, str], _Histogram] = {}
        self._seen: dict[tuple[str, float, str | None], None] = {}

    def observe(self, scans: Iterable[Scan]) -> None:
        """Note which PLCs delivered good data and how long failed requests took (called with
        every batch, before RBE)."""
        up = self._up
        good = Quality.GOOD
        for scan in scans:
            ok = True
            for s in scan.samples:
                ok = s.quality is good
                if not ok:
                    self._observe_failure(s)
            up[scan.plc] = ok  # as of the scan's last sample

    def forget(self, plcs: Collection[str]) -> None:
        """Drop the series of PLCs a reload removed: they are not exported any more."""
        for plc in plcs:
            self._up.pop(plc, None)
            self._histograms.pop(plc, None)
        for key in [k for k in self._failures if k[0] in plcs]:
            del self._failures[key]

    def _observe_failure(self, s: Sample) -> None:
        kind = s.error_type
        if kind is None or issubclass(kind, ValueDecodeError):
            return  # not a failed request: the value is bad, or the sample came without a type
        duration = s.receive_time - s.source_time
        if not duration > 0:
            return  # never sent: the rest of a scan after its connection was lost
        key = (s.plc, s.source_time, s.error)
        seen = self._seen
        if key in seen:
            return  # another tag of the same request
        seen[key] = None
        if len(seen) > SEEN_FAILURES:
            del seen[next(iter(seen))]
        h = self._failures.get((s.plc, kind.__name__))
        if h is None:
            h = self._failures[(s.plc, kind.__name__)] = _Histogram()
        h.add((duration,))

    def refresh(self) -> None:
        """Move the latencies added since the last call into the histograms."""
        for name, stats in self.poller.stats.items():
            h = self._histograms.get(name)
            if h is None:
                h = self._histograms[name] = _Histogram()
            window = stats.latencies
            new = window.total - h.seen
            if new > 0:
                h.add(window.tail(new))
                h.seen = window.total

    def collect(self) -> Iterator[Metric]:
        from prometheus_client.core import (
            CounterMetricFamily,
            GaugeMetricFamily,
            HistogramMetricFamily,
        )

        self.refresh()
        stats = self.poller.stats
        up = GaugeMetricFamily(
            "plcstack_plc_up", "1 if the PLC's latest sample was good", labels=["plc"]
        )
        for name in stats:
            up.add_metric([name], 1.0 if self._up.get(name) else 0.0)
        yield up
        counters = [
            ("requests", "requests sent to the PLC"),
            ("errors", "failed requests and writes"),
            ("reconnects", "connections re-established"),
            ("connect_failures", "failed connection attempts"),
            ("overruns", "scans that ran past their next due time"),
            ("samples", "samples delivered"),
            ("bad_samples", "samples of bad quality"),
            ("writes", "writes requested"),
        ]
        for field, doc in counters:
            family = CounterMetricFamily(f"plcstack_{field}", doc, labels=["plc"])
            for name, s in stats.items():
                family.add_metric([name], float(getattr(s, field)))
            yield family
        hist = HistogramMetricFamily(
            "plcstack_request_latency_seconds", "PLC request latency", labels=["plc"]
        )
        for name, h in self._histograms.items():
            hist.add_metric([name], h.buckets(), h.sum)
        yield hist
        failed = HistogramMetricFamily(
            "plcstack_failed_request_latency_seconds",
            "time from sending a request until it was known to have failed, per error type",
            labels=["plc", "error"],
        )
        for (name, kind), h in self._failures.items():
            failed.add_metric([name, kind], h.buckets(), h.sum)
        yield failed
        yield CounterMetricFamily(
            "plcstack_dropped_samples",
            "samples dropped because the consumer fell behind",
            value=float(self.poller.dropped),
        )
        faces = self.faces()
        sinks = self.sinks + [face for face in faces if isinstance(face, MqttSink)]
        if sinks:
            gauges: dict[str, tuple[str, Callable[[MqttSink], float]]] = {
                "plcstack_buffer_backlog_messages": ("messages waiting", lambda k: len(k.buffer)),
                "plcstack_buffer_backlog_bytes": (
                    "bytes waiting",
                    lambda k: k.buffer.backlog_bytes,
                ),
                "plcstack_mqtt_connected": ("1 while connected", lambda k: float(k.connected)),
            }
            for metric, (doc, get) in gauges.items():
                g = GaugeMetricFamily(metric, doc, labels=["sink"])
                for i, sink in enumerate(sinks):
                    g.add_metric([str(i)], float(get(sink)))
                yield g
            totals: dict[str, tuple[str, Callable[[MqttSink], float]]] = {
                "plcstack_buffer_dropped_messages": (
                    "messages lost: dropped by the byte budget or refused by a full disk",
                    lambda k: k.buffer.dropped,
                ),
                "plcstack_mqtt_sent": (
                    "messages acknowledged by the broker",
                    lambda k: k.stats.sent,
                ),
                "plcstack_mqtt_replayed": (
                    "messages sent after a reconnect",
                    lambda k: k.stats.replayed,
                ),
                "plcstack_mqtt_connection_failures": (
                    "failed connection attempts and dropped sessions (the log says why)",
                    lambda k: k.stats.failures,
                ),
            }
            for metric, (doc, get) in totals.items():
                c = CounterMetricFamily(metric, doc, labels=["sink"])
                for i, sink in enumerate(sinks):
                    c.add_metric([str(i)], float(get(sink)))
                yield c
        if self.supervisor is not None:
            errors = CounterMetricFamily(
                "plcstack_sink_errors",
                "samples a sink could not take and deaths of its task (the log says which)",
                labels=["sink"],
            )
            for name, count in sorted(self.supervisor.errors.items()):
                errors.add_metric([name], float(count))
            yield errors
        guarded = CounterMetricFamily(
            "plcstack_face_guard",
            "what each listening face did to protect its clients: connections refused"
            " (max_clients, max_clients_per_host) or closed (first_request_timeout,"
            " idle_timeout, frame_timeout), and malformed requests (malformed)",
            labels=["face", "reason"],
        )
        for (kind, reason), count in TOTALS.items():
            guarded.add_metric([kind, reason], float(count))
        yield guarded
        if self.rbe is not None:
            yield CounterMetricFamily(
                "plcstack_rbe_suppressed",
                "samples held back by report-by-exception",
                value=float(self.rbe.suppressed),
            )
        for face in faces:
            yield from face.metrics()


class MetricsServer(FaceBase):
    """Serves ``/metrics``, ``/healthz`` and ``/livez``; a face of the runtime (it takes no
    scans: the collector reads the poller's own counters). ``health()`` gives every part of
    the run (default: this server alone); ``supervisor``: the run's (default: its own), under
    which the histogram refresh runs."""

    name = "metrics"

    def __init__(
        self,
        collector: PlcstackCollector,
        settings: MetricsSettings | None = None,
        health: Callable[[], list[Health]] | None = None,
        *,
        supervisor: Supervisor | None = None,
    ) -> None:
        from prometheus_client import CollectorRegistry

        self.collector = collector
        self.settings = settings or MetricsSettings()
        self.parts = health if health is not None else lambda: [self.health()]
        self.supervisor = supervisor if supervisor is not None else Supervisor()
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(collector)
        self._server: asyncio.Server | None = None
        self._refresher: Supervised | None = None
        self._handlers: set[asyncio.Task[Any]] = set()
        #: clients at once and per host, the first request's deadline; what they refused
        self.guard = FaceGuard("metrics", "metrics endpoint", self.settings.limits, log)
        self.port = self.settings.port

    @property
    def url(self) -> str:
        return f"http://{self.settings.host}:{self.port}/metrics"

    def submit(self, scans: Sequence[Scan]) -> None:
        """Nothing to take: the collector reads the run's counters when it is scraped."""

    def health(self) -> Health:
        if self._server is None:
            return Health(self.name, f"not listening on {self.settings.host}:{self.settings.port}")
        return Health(self.name)

    async def start(self) -> None:
        """Listen; :class:`ConfigError` naming the address if that is not possible (a port
        taken, e.g. by a second process started from the same file)."""
        host, port = self.settings.host, self.settings.port
        try:
            self._server = await asyncio.start_server(self._handle, host, port, limit=MAX_REQUEST)
        except OSError as exc:
            raise ConfigError(
                f"[metrics] cannot serve /metrics on {self.settings.listen}: "
                f"{exc.strerror or exc} (another process on that port? set [metrics] listen)"
            ) from None
        self.port = self._server.sockets[0].getsockname()[1]
        self.guard.announce(f"{host}:{self.port}")
        self._refresher = self.supervisor.start("metrics refresh", self._refresh_loop)

    async def _refresh_loop(self) -> None:
        while True:
            await asyncio.sleep(1.0)
            self.collector.refresh()

    async def aclose(self) -> None:
        if self._refresher is not None:
            await self._refresher.stop()
            self._refresher = None
        server, self._server = self._server, None
        if server is not None:
            server.close()
        handlers = list(self._handlers)
        await cancel_until_done(handlers)  # a handler may drop one cancel (Python 3.11)
        await asyncio.gather(*handlers, return_exceptions=True)
        if server is not None:
            await server.wait_closed()
        self.guard.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        visit = self.guard.admit(writer.get_extra_info("peername"))
        if visit is None:
            writer.transport.abort()
            return
        task = asyncio.current_task()
        if task is not None:
            self._handlers.add(task)
        try:
            try:
                # the request within the first request's deadline (silent or trickled: closed)
                async with asyncio.timeout_at(visit.due):
                    head = await reader.readuntil(b"\r\n\r\n")
            except asyncio.LimitOverrunError:
                head = b"TOO-LARGE / HTTP/1.1\r\n\r\n"
            except TimeoutError:
                visit.expired()  # counted and said by the guard
                return
            visit.served()
            # a deadline for the answer too: it waits for a client that does not read it
            async with asyncio.timeout(REQUEST_TIMEOUT):
                await self._answer(head, writer)
        except TimeoutError:
            pass  # a client too slow to read its answer
        except (asyncio.IncompleteReadError, ConnectionError):
            pass  # the client left before its request was complete
        except asyncio.CancelledError:
            pass  # the server stops: end normally (Python 3.11 logs a cancelled handler)
        finally:
            self._handlers.discard(task)
            visit.leave()
            await close_writer(writer)  # aborted if the client does not read its answer

    async def _answer(self, head: bytes, writer: asyncio.StreamWriter) -> None:
        try:
            request_line = head.split(b"\r\n", 1)[0].decode("latin-1")
            parts = request_line.split()
            method, path = (parts[0], parts[1]) if len(parts) >= 2 else ("", "")
            path = path.split("?", 1)[0]
            if method == "TOO-LARGE":
                status, ctype, body = "431 Request Header Fields Too Large", "text/plain", b"\n"
            elif path not in ("/metrics", "/healthz", "/livez"):
                status, ctype, body = "404 Not Found", "text/plain", b"not found\n"
            elif method not in ("GET", "HEAD"):
                status, ctype, body = "405 Method Not Allowed", "text/plain", b"GET only\n"
            elif path == "/livez":
                status, ctype, body = "200 OK", "text/plain", b"alive\n"
            elif path == "/healthz":
                healthy, text = healthz_body(self.parts())
                status = "200 OK" if healthy else "503 Service Unavailable"
                ctype, body = "text/plain; charset=utf-8", text.encode()
            else:
                from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

                status, ctype, body = "200 OK", CONTENT_TYPE_LATEST, generate_latest(self.registry)
            writer.write(
                f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
                "Connection: close\r\n\r\n".encode()
            )
            if method != "HEAD":
                writer.write(body)
            await writer.drain()
        except (
            asyncio.IncompleteReadError,
            asyncio.LimitOverrunError,
            ConnectionError,
        ):
            pass
