"""``GET /api/plcs/NAME/capture.pcapng``: a PLC's last frames from the flight recorder.

What ``[trace] ring`` keeps of the PLC's connection, as a pcapng file to open in Wireshark
(``docs/wire.md``), sent as an attachment named for the PLC and the time. As every ``GET`` of
the REST API it needs no token: it shows what the console's pages show, the bytes they came in.
Without ``[trace]`` it is answered 404 ``no_trace``, a PLC the console does not know 404
``unknown_plc``.
"""

from __future__ import annotations

import re
import time
from typing import Protocol

from aiohttp import web

from plcstack.north.trace import TraceSink
from plcstack.north.web.api import refusal
from plcstack.north.web.state import ConsoleState

__all__ = ["capture_routes"]


class CaptureConsole(Protocol):
    """What the route needs of the console: its state (the PLC names), the flight recorder."""

    state: ConsoleState
    trace: TraceSink | None


def capture_routes(console: CaptureConsole) -> list[web.RouteDef]:
    async def capture(request: web.Request) -> web.Response:
        plc = request.match_info["plc"]
        if plc not in console.state.plcs:
            return refusal("unknown_plc", f"no PLC named {plc[:100]!r} here")
        trace = console.trace
        if trace is None:
            return refusal(
                "no_trace",
                "this gateway records no frames: add a [trace] table to its configuration",
            )
        body = trace.capture(plc)
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        name = f"{re.sub(r'[^A-Za-z0-9._-]+', '_', plc)}-{stamp}.pcapng"
        return web.Response(
            body=body,
            content_type="application/x-pcapng",
            headers={"Content-Disposition": f'attachment; filename="{name}"'},
        )

    return [web.get("/api/plcs/{plc}/capture.pcapng", capture)]
