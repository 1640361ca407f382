""":class:`WebConsole`: the console's aiohttp application, run on the poller's own event loop.

A north-side sink like the others: ``start()``, ``submit(scans)`` (the state takes the samples;
nothing is sent from there), ``aclose()``. Binds 127.0.0.1 unless ``[web] host`` says otherwise:
the pages name every PLC of the plant. Every response carries a Content-Security-Policy that
allows scripts, styles and connections from the console itself only (no inline script), and
``nosniff``; request bodies are limited to 64 KiB. A request for a host name the console does
not serve is answered 421 before any route (DNS rebinding, see :mod:`.hosts`). The console's
face guard (:mod:`plcstack.transports.guard`, ``[web]`` limits) serves at most ``max_clients``
connections, ``max_clients_per_host`` of them from one host (the next get 503 and are closed:
a flood cannot take the file descriptors the PLC connections need), closes a connection that
sends no complete request header within ``first_request_timeout`` (silent, or a header
trickled byte by byte) and one that waits ``idle_timeout`` between requests; a request that
cannot be parsed is answered 400, and said once per host per burst with the count.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import sys
from collections.abc import Awaitable, Callable, Sequence
from importlib import resources
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from plcstack.errors import ConfigError
from plcstack.north.control import ConfigControl
from plcstack.north.face import FaceBase, PlcUpdate, PollerView
from plcstack.north.health import Health, healthz_body
from plcstack.north.history import History
from plcstack.north.supervise import Supervised, Supervisor
from plcstack.north.trace import TraceSink
from plcstack.north.web.api import MAX_PENDING_WRITES, peer_of, refusal, routes
from plcstack.north.web.capture import capture_routes
from plcstack.north.web.config_api import config_routes
from plcstack.north.web.events import EventClient, EventHub
from plcstack.north.web.history import history_routes
from plcstack.north.web.hosts import HostCheck
from plcstack.north.web.overview import Selection, select
from plcstack.north.web.pages import esc, overview_page
from plcstack.north.web.plc_page import plc_page
from plcstack.north.web.settings import WebSettings
from plcstack.north.web.state import ConsoleState, PlcRow, plc_row
from plcstack.north.writes import WritePath
from plcstack.poll.samples import Scan
from plcstack.transports.guard import FaceGuard, GuardedProtocol

__all__ = ["WebConsole"]

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

log = logging.getLogger("plcstack.web")

MAX_BODY = 64 * 1024
#: the write audit's ``source`` of writes from the console and the REST API
SOURCE = "web"
#: a stream with nothing to say sends a comment this often (finds peers that went away)
KEEPALIVE = 15.0
_BUSY = (
    b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: 26\r\n"
    b"Connection: close\r\n\r\ntoo many connections open\n"
)
_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self';"
        " img-src 'self'; form-action 'self'; base-uri 'none'; frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}
_STATIC = {"console.js": "text/javascript", "console.css": "text/css"}
_compact = functools.partial(json.dumps, separators=(",", ":"))
#: PLC rows an overview's stream may ask for (a page shows 50)
MAX_SHOWN = 200


class WebConsole(FaceBase):
    """The web console and REST API of one poller (see the package docstring); a face of the
    runtime (:class:`~plcstack.north.face.Face`). ``writes``: the run's one write path
    (default: one on ``poller`` without an audit); ``supervisor``: the run's (default: its
    own); ``health``: every part of the run, for ``/healthz``; ``history``: the run's embedded
    history, if it has one; ``control``: the running configuration (``/api/config``; None: the
    run cannot be reconfigured)."""

    def __init__(
        self,
        poller: PollerView,
        settings: WebSettings | None = None,
        *,
        writes: WritePath | None = None,
        supervisor: Supervisor | None = None,
        health: Callable[[], list[Health]] | None = None,
        history: History | None = None,
        reachable: Callable[[str], bool | None] | None = None,
        trace: TraceSink | None = None,
        control: ConfigControl | None = None,
    ) -> None:
        self.poller = poller
        #: the running configuration: shown, read again, replaced (None: not reconfigurable)
        self.control = control
        #: every part of the run, for ``/healthz`` (default: this console alone)
        self.parts = health if health is not None else lambda: [self.health()]
        #: the embedded history the trends and ``/api/history`` read (None: not configured)
        self.history = history
        #: the flight recorder the capture download reads (None: no ``[trace]``)
        self.trace = trace
        self.writes = writes if writes is not None else WritePath(poller)
        self.settings = settings or WebSettings()
        self.state = ConsoleState(
            poller.config.plcs, trend_seconds=self.settings.trend_seconds, reachable=reachable
        )
        self.hub = EventHub(self.state, self.plc_rows)
        self.port = self.settings.port
        #: the write token, read from the environment at start (None: writes are off)
        self.token: str | None = None
        self._runner: web.AppRunner | None = None
        self._listener: asyncio.Server | None = None
        #: connections at once and per host, first request, idle; what they refused and closed
        self.guard = FaceGuard("web", "web console", self.settings.limits, log)
        #: runs the push to the browsers
        self.supervisor = supervisor if supervisor is not None else Supervisor()
        self._pusher: Supervised | None = None
        self._writes: set[asyncio.Task[Any]] = set()
        files = resources.files(__package__ or "plcstack.north.web")
        self._static = {name: (files / name).read_bytes() for name in _STATIC}
        #: which ``Host`` is served; ``hosts.refused`` counts the requests turned away
        self.hosts = HostCheck(self.settings.host, self.settings.hosts, log)

    #: how logs, metrics and ``/healthz`` name it
    name = "web console"

    @property
    def url(self) -> str:
        return f"http://{self.settings.host}:{self.port}/"

    # -- the sink protocol ----------------------------------------------------------------------
    def submit(self, scans: Sequence[Scan]) -> None:
        self.state.submit(scans)

    async def update_plcs(self, update: PlcUpdate) -> None:
        """A removed PLC's row is gone, an added one's appears (see
        :meth:`ConsoleState.reconfigure`)."""
        self.state.reconfigure(update.view.config.plcs, update.changed)

    async def start(self) -> None:
        """Listen; a :class:`ConfigError` naming the address if that is not possible."""
        self.token = self.settings.write_token()
        hosts = self.hosts

        @web.middleware
        async def served_hosts(request: web.Request, handler: Handler) -> web.StreamResponse:
            # before any route: a page rebinding its own name to ours reads nothing
            header = request.headers.get("Host")
            if hosts.serves(header):
                return await handler(request)
            assert header is not None
            hosts.refused_request(header, peer_of(request), request.path)
            return web.Response(
                status=421,
                text="this console does not serve that host name; if it is yours, add it to"
                " [web] hosts\n",
            )

        app = web.Application(client_max_size=MAX_BODY, middlewares=[served_hosts])
        app.on_response_prepare.append(_secure)
        app.add_routes(
            [
                web.get("/", self._overview),
                web.get("/api/overview", self._overview_api),
                web.get("/plc/{plc}", self._plc),
                web.get("/events", self._events),
                web.get("/static/{name}", self._file),
                web.get("/healthz", self._healthz),
                web.get("/livez", self._livez),
                *routes(self),
                *history_routes(self),
                *capture_routes(self),
                *config_routes(self),
            ]
        )
        http_log = logging.Logger(_http_log.name)  # not in the registry: it goes with the console
        http_log.parent = _http_log
        http_log.addFilter(_ClientFaults(self.guard))
        runner = web.AppRunner(
            app,
            access_log=None,
            handle_signals=False,
            shutdown_timeout=1.0,
            # between requests (0: never); the first request is the guard's
            keepalive_timeout=self.settings.limits.idle_timeout or 0,
            logger=http_log,
        )
        await runner.setup()
        host, port = self.settings.host, self.settings.port
        http = runner.server
        assert http is not None
        guard = self.guard

        def accept() -> asyncio.BaseProtocol:
            # aiohttp has no connection limit: the guard admits, one it refuses gets 503
            return GuardedProtocol(guard, http, b"\r\n\r\n", _busy)

        try:
            # not web.TCPSite: aiohttp has no connection limit, so the listener is ours
            listener = await asyncio.get_running_loop().create_server(accept, host, port)
        except OSError as exc:
            await runner.cleanup()
            raise ConfigError(
                f"[web] cannot serve the console on {host}:{port}: {exc.strerror or exc}"
                " (another process on that port? set [web] port or --web-port)"
            ) from None
        self._runner, self._listener = runner, listener
        self.port = listener.sockets[0].getsockname()[1]  # the port taken when [web] port = 0
        guard.announce(self.url)
        self._pusher = self.supervisor.start(self.name, self.hub.run)
        # where to point the browser, on stderr as the simulators say where they listen
        print(
            f"plcstack: web console on {self.url} (writes {'on' if self.token else 'off'})",
            file=sys.stderr,
            flush=True,
        )

    def health(self) -> Health:
        if self._listener is None:
            return Health(self.name, f"not listening on {self.settings.host}:{self.settings.port}")
        return Health(self.name, figures=(("browsers", len(self.hub.clients)),))

    async def aclose(self) -> None:
        if self._pusher is not None:
            await self._pusher.stop()
            self._pusher = None
        for client in list(self.hub.clients):
            client.close()
        for task in list(self._writes):
            task.cancel()
        if self._writes:
            await asyncio.gather(*self._writes, return_exceptions=True)
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if listener is not None:
            await listener.wait_closed()
        self.guard.close()

    # -- data -----------------------------------------------------------------------------------
    def plc_rows(self, plc: str | None) -> list[PlcRow]:
        return self.rows_of(list(self.state.health) if plc is None else [plc])

    def rows_of(self, names: list[str]) -> list[PlcRow]:
        """The rows of these PLCs (health, counters, how many tags)."""
        stats = self.poller.stats
        health, plcs = self.state.health, self.state.plcs
        return [
            plc_row(name, health[name], stats.get(name), len(plcs[name].tags)) for name in names
        ]

    def _select(self, request: web.Request) -> Selection:
        query = request.query
        return select(
            self.state.plcs,
            self.state.health,
            query=query.get("q", ""),
            sort=query.get("sort", "state"),
            page=query.get("page", "1"),
        )

    async def write(self, plc: str, tag: str, value: object, *, peer: str | None) -> web.Response:
        """One write from the web, after the token was checked (see :mod:`.api`): through the
        north side's one write path (allow-list, value grammar, ``write_tag``, audit with the
        HTTP client's address as ``peer``)."""
        if len(self._writes) >= MAX_PENDING_WRITES:
            return self.refuse(
                plc, tag, value, "busy", "too many writes waiting; not attempted", peer=peer
            )
        task = asyncio.create_task(self.writes.write(SOURCE, None, plc, tag, value, peer=peer))
        self._writes.add(task)
        task.add_done_callback(self._writes.discard)
        # shielded: a browser that goes away does not cancel a write half done
        result = await asyncio.shield(task)
        if result.ok:
            return web.json_response({"ok": True})
        return refusal(result.code, result.message, result.may_have_executed)

    def refuse(
        self,
        plc: str,
        tag: str,
        value: object,
        code: str,
        message: str,
        *,
        peer: str | None,
        status: int | None = None,
    ) -> web.Response:
        """A refusal decided here (token, body, too many): logged and audited as every other;
        ``status`` instead of the code's own (413 for a body too large)."""
        self.writes.refuse(SOURCE, None, plc, tag, value, code, message, peer=peer)
        return refusal(code, message, status=status)

    # -- pages ----------------------------------------------------------------------------------
    async def _overview(self, request: web.Request) -> web.Response:
        selection = self._select(request)
        return _html(
            overview_page(
                self.state,
                selection,
                self.rows_of(selection.names),
                trend_seconds=self.settings.trend_seconds,
                history=self.history is not None,
            )
        )

    async def _overview_api(self, request: web.Request) -> web.Response:
        """``GET /api/overview?q=&sort=&page=``: what the overview page shows, as JSON."""
        selection = self._select(request)
        return web.json_response(
            {
                "counts": self.state.counts(),
                "query": selection.query,
                "sort": selection.sort,
                "matched": selection.matched,
                "page": selection.page,
                "pages": selection.pages,
                "first": selection.first,
                "rows": self.rows_of(selection.names),
            },
            dumps=_compact,
        )

    async def _plc(self, request: web.Request) -> web.Response:
        plc = request.match_info["plc"]
        if plc not in self.state.plcs:
            return _html(f"<!doctype html><title>not found</title>no PLC {esc(plc)}", 404)
        return _html(
            plc_page(
                self.state,
                plc,
                self.plc_rows(plc),
                trend_seconds=self.settings.trend_seconds,
                writes_enabled=self.token is not None,
                history=self.history is not None,
                capture=self.trace is not None,
            )
        )

    async def _healthz(self, request: web.Request) -> web.Response:
        """200 while every part of the run is healthy, else 503 naming each that is not."""
        healthy, text = healthz_body(self.parts())
        return web.Response(text=text, status=200 if healthy else 503, content_type="text/plain")

    async def _livez(self, request: web.Request) -> web.Response:
        """200 while the process runs (and its event loop answers)."""
        return web.Response(text="alive\n", content_type="text/plain")

    async def _file(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in self._static:
            raise web.HTTPNotFound()
        return web.Response(
            body=self._static[name],
            content_type=_STATIC[name],
            headers={"Cache-Control": "no-cache"},
        )

    async def _events(self, request: web.Request) -> web.StreamResponse:
        plc = request.query.get("plc") or None
        if plc is not None and plc not in self.state.plcs:
            return refusal("unknown_plc", f"no PLC named {plc!r} here")
        overview = request.query.get("view") == "overview"
        shown = request.query.getall("show", [])[:MAX_SHOWN] if "show" in request.query else None
        client = self.hub.connect(plc, overview=overview, names=shown)
        if client is None:
            raise web.HTTPServiceUnavailable(text="too many browsers connected\n")
        transport = request.transport
        if transport is not None:
            client.on_drop = transport.abort
        response = web.StreamResponse(
            headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"}
        )
        try:
            await response.prepare(request)
            await _stream(client, response)
        except (ConnectionError, RuntimeError):
            pass  # the browser went away, or was dropped for not reading
        finally:
            self.hub.disconnect(client)
        return response


async def _stream(client: EventClient, response: web.StreamResponse) -> None:
    while True:
        try:
            async with asyncio.timeout(KEEPALIVE):
                data = await client.next()
        except TimeoutError:
            data = b": keepalive\n\n"
        if data is None:
            return
        await response.write(data)


def _busy(transport: asyncio.Transport) -> None:
    """A connection the guard refused: 503 and closed, nothing read."""
    transport.write(_BUSY)
    transport.close()


class _ClientFaults(logging.Filter):
    """aiohttp logs a request it cannot parse (garbage, a port scanner, a bad Content-Length)
    as an ERROR with a traceback, which reads like a fault of the console. It is the client's:
    said by the console's guard, once per host per burst with the count."""

    def __init__(self, guard: FaceGuard) -> None:
        super().__init__()
        self.guard = guard

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if not isinstance(exc, HttpProcessingError):
            return True
        peer = record.args[0] if isinstance(record.args, tuple) and record.args else None
        what = " ".join(str(exc.message).split())[:200]
        host = str(peer) if peer else None
        self.guard.malformed(host, host, f"a bad HTTP request, answered {exc.code}: {what}")
        return False


#: the logger of aiohttp's connections: each console logs to a child of its own, whose filter
#: hands the clients' faults to the console's guard
_http_log = logging.getLogger("plcstack.web.http")


def _html(text: str, status: int = 200) -> web.Response:
    return web.Response(text=text, status=status, content_type="text/html", charset="utf-8")


async def _secure(request: web.Request, response: web.StreamResponse) -> None:
    response.headers.update(_HEADERS)
