"""The REST API: the console's data for scripts, and writes with a bearer token.

```
GET  /api/plcs                      [{name, up, last_error, error_time, requests, errors,
                                      reconnects, p50_ms, p99_ms}, ...]
GET  /api/tags[?plc=NAME]           [{plc, tag, value, quality, source_time, error}, ...]
GET  /api/plcs/{plc}/tags/{tag}/trend   [[unix_time, value], ...] oldest first
POST /api/plcs/{plc}/tags/{tag}     {"value": v} with "Authorization: Bearer TOKEN"
                                    -> {"ok": true}
                                    or {"ok": false, "error": CODE, "message": ...,
                                        "may_have_executed": ...}
```

Write refusals, in the order they are checked: writes off (no token configured) 403
``not_writable``; no or wrong token (any bytes) 401 ``unauthorized``; a body over 64 KiB 413
``bad_request``; a body that is not ``{"value": v}`` in UTF-8 JSON 400 ``bad_request``;
unknown PLC or tag 404 ``unknown_plc``/``unknown_tag``; a tag without ``writable = true`` 403
``not_writable``; too many writes waiting 503 ``busy``; a value the tag's type cannot take 400
``wrong_type``; the PLC refused or did not answer 502 ``plc_error`` (with ``may_have_executed``
true when the request was sent and its outcome is unknown). The codes are
the MQTT write codes. The token is compared in constant time; nothing writes through ``GET``.
Every attempt that reaches this route is logged and audited, each refusal above included; no
malformed header or body is a 500.
"""

from __future__ import annotations

import hmac
import json
from typing import Any, Protocol

from aiohttp import web

from plcstack.north.web.state import ConsoleState, PlcRow, tag_row
from plcstack.transports.peer import peer_address

__all__ = ["MAX_PENDING_WRITES", "ConsoleApi", "json_body", "peer_of", "routes"]


class ConsoleApi(Protocol):
    """What the routes need of the console: its state, the PLC rows, the write token and the
    write path. A protocol here, so the API does not import the server that mounts it."""

    state: ConsoleState
    token: str | None

    def plc_rows(self, plc: str | None) -> list[PlcRow]: ...

    async def write(
        self, plc: str, tag: str, value: object, *, peer: str | None
    ) -> web.Response: ...

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
    ) -> web.Response: ...


#: writes in flight at once from the web; more are refused with ``busy``
MAX_PENDING_WRITES = 16

_STATUS = {
    "unauthorized": 401,
    "not_writable": 403,
    "bad_request": 400,
    "wrong_type": 400,
    "unknown_plc": 404,
    "unknown_tag": 404,
    "no_history": 404,
    "no_trace": 404,
    "busy": 503,
    "plc_error": 502,
}


def _json(data: Any, status: int = 200) -> web.Response:
    return web.Response(
        text=json.dumps(data, separators=(",", ":")),
        status=status,
        content_type="application/json",
    )


def refusal(
    code: str, message: str, may_have_executed: bool = False, *, status: int | None = None
) -> web.Response:
    """A refused request's answer; ``status`` instead of the code's own."""
    response = _json(
        {"ok": False, "error": code, "message": message, "may_have_executed": may_have_executed},
        _STATUS[code] if status is None else status,
    )
    if code == "unauthorized":
        response.headers["WWW-Authenticate"] = 'Bearer realm="plcstack"'
    return response


def token_matches(header: str | None, token: str) -> bool:
    """``Authorization: Bearer TOKEN``, compared in constant time. Any bytes are a token that
    does not match (aiohttp hands undecodable header bytes over as surrogates)."""
    if header is None or not header.startswith("Bearer "):
        return False
    given = header[len("Bearer ") :].strip().encode("utf-8", "surrogateescape")
    return hmac.compare_digest(given, token.encode("utf-8", "surrogateescape"))


def json_body(raw: bytes) -> tuple[Any, str | None]:
    """A write's body ``{"value": v}``: (the object, None), or (None, what is wrong with it).

    UTF-8 whatever the ``Content-Type`` says (JSON between systems is UTF-8, RFC 8259; a
    charset Python does not know must not turn into a 500), nesting too deep for the decoder
    is a bad request like any other malformed body."""
    try:
        body = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        return None, "the body is not UTF-8 text; not attempted"
    except RecursionError:
        return None, "the body is nested too deeply to be a value; not attempted"
    except ValueError:
        body = None
    if not isinstance(body, dict) or "value" not in body:
        return None, 'the body must be a JSON object {"value": ...}; not attempted'
    return body, None


def peer_of(request: web.Request) -> str | None:
    """The HTTP client's address (a reverse proxy's, when one is in front)."""
    transport = request.transport
    return peer_address(transport.get_extra_info("peername") if transport else None)


def routes(console: ConsoleApi) -> list[web.RouteDef]:
    state = console.state

    async def plcs(request: web.Request) -> web.Response:
        return _json(console.plc_rows(None))

    async def tags(request: web.Request) -> web.Response:
        plc = request.query.get("plc")
        if plc is not None and plc not in state.plcs:
            return refusal("unknown_plc", f"no PLC named {plc!r} here")
        return _json(
            [tag_row(state, s) for s in state.latest.values() if plc is None or s.plc == plc]
        )

    async def trend(request: web.Request) -> web.Response:
        plc, tag = request.match_info["plc"], request.match_info["tag"]
        if (plc, tag) not in state.tags:
            code = "unknown_tag" if plc in state.plcs else "unknown_plc"
            return refusal(code, f"no tag {tag!r} of a PLC {plc!r} here")
        return _json([[t, v] for t, v in state.trend(plc, tag)])

    async def write(request: web.Request) -> web.Response:
        plc, tag = request.match_info["plc"], request.match_info["tag"]
        # the HTTP client's address for the audit (a reverse proxy's, when one is in front)
        peer = peer_of(request)
        token = console.token
        if token is None:
            return console.refuse(
                plc,
                tag,
                None,
                "not_writable",
                "writes are off: the console was started without a write token"
                " ([web] write_token_env names an environment variable that is not set)",
                peer=peer,
            )
        if not token_matches(request.headers.get("Authorization"), token):
            return console.refuse(
                plc,
                tag,
                None,
                "unauthorized",
                f"a valid 'Authorization: Bearer TOKEN' is required (request from"
                f" {request.remote}); not attempted",
                peer=peer,
            )
        try:
            raw = await request.read()
        except web.HTTPRequestEntityTooLarge:
            return console.refuse(
                plc,
                tag,
                None,
                "bad_request",
                f"the body is larger than {request.client_max_size} bytes; not attempted",
                peer=peer,
                status=413,
            )
        body, problem = json_body(raw)
        if problem is not None:
            return console.refuse(plc, tag, None, "bad_request", problem, peer=peer)
        assert isinstance(body, dict)
        return await console.write(plc, tag, body["value"], peer=peer)

    return [
        web.get("/api/plcs", plcs),
        web.get("/api/tags", tags),
        web.get("/api/plcs/{plc}/tags/{tag}/trend", trend),
        web.post("/api/plcs/{plc}/tags/{tag}", write),
    ]
