"""The running configuration over REST: shown with its secrets redacted, read again, replaced.

```
GET  /api/config            the running file's text, secrets redacted (application/toml)
POST /api/config/reload     read the file again and apply it
POST /api/config            a whole TOML text as the body: checked, written (FILE.bak kept),
                            applied
-> {"ok": true, "summary": "PLCs added: ...; removed: ...; changed: ..."}
   or {"ok": false, "errors": ["FILE:LINE: ...", ...]}
```

All three need ``Authorization: Bearer TOKEN``, the write token (the file names every PLC,
address and path of the plant): 403 while the console has no token, 401 without it or with
another. A file that does not load is 400 with the same ``FILE:LINE`` errors as at start, and
nothing changes; a body over :data:`MAX_CONFIG_BYTES` is 413, one that is not UTF-8 400; 409
while another change from the console is being applied; 503 when the run cannot be
reconfigured (no :class:`~plcstack.north.control.ConfigControl`).

Secrets (:mod:`plcstack.redact`): ``GET`` shows each as ``<redacted:ID>``. A text sent back
with such a marker keeps the running secret it stands for, so a file can be fetched, edited
and sent back without anyone seeing its secrets; a marker that stands for no running secret
(shown by an earlier run, or the secret changed since) is refused with its line, and no file
is ever written with a marker in it.

A change refused here (no token or a wrong one, too large, not UTF-8, another change running, a
marker that stands for no running secret) is said once per client per burst at WARNING and is
one record of the ``[audit]`` (``"kind": "config"``, ``"result": "refused"``), as the runtime
records each change it applies or refuses.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import time
from collections.abc import Coroutine
from typing import Protocol

from aiohttp import web

from plcstack.north.control import ApplyOutcome, ConfigControl
from plcstack.north.web.api import peer_of, token_matches
from plcstack.north.writes import WritePath
from plcstack.redact import RedactionError, redact, restore
from plcstack.transports.guard import FaceGuard

__all__ = ["MAX_CONFIG_BYTES", "ConfigConsole", "config_routes"]

log = logging.getLogger("plcstack.web")

#: the largest configuration text ``POST /api/config`` takes (a plant of 1000 PLCs with ten
#: tags each is about 600 KiB)
MAX_CONFIG_BYTES = 4 << 20
_compact = functools.partial(json.dumps, separators=(",", ":"))


class ConfigConsole(Protocol):
    """What the routes need of the console: its write token, the running configuration's
    control, its guard (refusals said once per client per burst) and the run's write path
    (whose audit records each refused change)."""

    token: str | None
    control: ConfigControl | None
    guard: FaceGuard
    writes: WritePath


def _answer(status: int, errors: list[str]) -> web.Response:
    response = web.json_response({"ok": False, "errors": errors}, status=status, dumps=_compact)
    if status == 401:
        response.headers["WWW-Authenticate"] = 'Bearer realm="plcstack"'
    return response


def _outcome(outcome: ApplyOutcome) -> web.Response:
    if outcome.ok:
        return web.json_response({"ok": True, "summary": outcome.summary}, dumps=_compact)
    return _answer(400, list(outcome.errors))


def config_routes(console: ConfigConsole) -> list[web.RouteDef]:
    busy = asyncio.Lock()  # one change from the console at a time; the next is told so

    def refused(request: web.Request, status: int, message: str) -> web.Response:
        """A refusal decided here: said once per client per burst and, for a change (a
        ``POST``), one record of the audit, as every write refused on its route is."""
        peer = peer_of(request) or "?"
        host = request.remote or peer
        audit = console.writes.audit
        if request.method == "POST" and audit is not None:
            authorized = status not in (401, 403)
            audit.config_change(
                source=f"web {peer}" + (" (token)" if authorized else ""),
                file=str(console.control.path) if console.control is not None else "",
                ok=False,
                summary=message,
                now=time.time(),
            )
        console.guard.bursts.event(
            (host, f"config {status}"),
            f"web console: refused {request.method} {request.path} from {peer}: {message}"
            f" (more from {host} are counted and said once a minute)",
            f"web console: {{n}} more {request.method} {request.path} of {host} refused since"
            f" {{since}}: {message}",
        )
        return _answer(status, message.splitlines())

    def check(request: web.Request) -> tuple[ConfigControl | None, web.Response | None]:
        """The control, or the refusal: no token, a wrong one, a run without control."""
        token = console.token
        if token is None:
            return None, refused(
                request,
                403,
                "the configuration API is off: the console was started without a write token"
                " ([web] write_token_env names an environment variable that is not set)",
            )
        if not token_matches(request.headers.get("Authorization"), token):
            return None, refused(
                request,
                401,
                f"a valid 'Authorization: Bearer TOKEN' is required (request from"
                f" {request.remote})",
            )
        if console.control is None:
            return None, refused(
                request, 503, "this run cannot change its configuration (no configuration file)"
            )
        return console.control, None

    def who(request: web.Request) -> str:
        return f"web {peer_of(request) or '?'} (token)"

    async def show(request: web.Request) -> web.Response:
        control, refusal = check(request)
        if control is None:
            assert refusal is not None
            return refusal
        try:
            # in a thread: a plant's file of 1 MB takes a good part of a second
            text = await asyncio.to_thread(redact, control.text())
        except RedactionError as exc:
            log.error("web console: GET /api/config: %s", exc)
            return _answer(503, [str(exc)])
        return web.Response(text=text, content_type="application/toml", charset="utf-8")

    def apply(run: Coroutine[object, object, ApplyOutcome]) -> asyncio.Future[ApplyOutcome]:
        """Start one change; ``busy`` (taken by the caller) is released when it ends. The
        change is shielded by the caller: a client that goes away (or a change that restarts
        this console) does not cut it in half; its log line and audit record say how it
        ended."""
        task = asyncio.ensure_future(run)
        task.add_done_callback(_released)
        return task

    def _released(task: asyncio.Future[ApplyOutcome]) -> None:
        busy.release()
        if not task.cancelled() and (exc := task.exception()) is not None:
            log.error("web console: a configuration change failed: %r", exc, exc_info=exc)

    async def reload(request: web.Request) -> web.Response:
        control, refusal = check(request)
        if control is None:
            assert refusal is not None
            return refusal
        if busy.locked():
            return refused(request, 409, "another configuration change is being applied")
        await busy.acquire()  # free: taken at once
        return _outcome(await asyncio.shield(apply(control.reload(who=who(request)))))

    async def replace(request: web.Request) -> web.Response:
        control, refusal = check(request)
        if control is None:
            assert refusal is not None
            return refusal
        # taken before the body is read: one body of up to 4 MiB in memory at a time
        if busy.locked():
            return refused(request, 409, "another configuration change is being applied")
        await busy.acquire()  # free: taken at once
        try:
            text, refusal = await replacement(request, control)
        except BaseException:
            busy.release()
            raise
        if text is None:
            busy.release()
            assert refusal is not None
            return refusal
        return _outcome(await asyncio.shield(apply(control.replace(text, who=who(request)))))

    async def replacement(
        request: web.Request, control: ConfigControl
    ) -> tuple[str | None, web.Response | None]:
        """The body as the text to apply, its markers replaced by the running secrets; or
        the refusal (too large, not UTF-8, a marker that stands for no running secret)."""
        raw, problem = await _body(request)
        if raw is None:
            return None, refused(request, 413, problem or "")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            why = f"the body is not UTF-8 text ({exc.reason} at byte {exc.start})"
            return None, refused(request, 400, why)
        try:
            # in a thread: a plant's file of 1 MB takes a good part of a second
            path = str(control.path)
            return await asyncio.to_thread(restore, text, control.text(), source=path), None
        except RedactionError as exc:
            return None, refused(request, 400, str(exc))

    return [
        web.get("/api/config", show),
        web.post("/api/config/reload", reload),
        web.post("/api/config", replace),
    ]


async def _body(request: web.Request) -> tuple[bytes | None, str | None]:
    """The body, read up to :data:`MAX_CONFIG_BYTES` (not the console's 64 KiB for other
    requests: a plant's file is larger); ``(None, why)`` for one too large."""
    too_large = f"the body is larger than {MAX_CONFIG_BYTES} bytes"
    length = request.content_length
    if length is not None and length > MAX_CONFIG_BYTES:
        return None, too_large
    chunks: list[bytes] = []
    size = 0
    while chunk := await request.content.read(64 * 1024):
        size += len(chunk)
        if size > MAX_CONFIG_BYTES:
            return None, too_large
        chunks.append(chunk)
    return b"".join(chunks), None
