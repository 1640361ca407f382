"""The walk of one polled E71 read, and of one scan's samples through the north side: every
plcstack function entered, in order, with the files crossed. Generated, not typed: the two
figures of ARCHITECTURE.md are this module's output, and a test checks they are current.

``python -m plcstack.bench.walk`` prints both; ``python -m plcstack.bench.walk --write
ARCHITECTURE.md`` replaces them there (between the ``walk:request`` and ``walk:north`` markers).

The request walk polls one PLC (a fixed-reply E71 responder on loopback, one tag of 64 words)
until its scans run the usual way (the read checked once, the connection settled), then traces
one scan with :func:`sys.setprofile`: the calls made under the ticker's callback (the scan is
due, its request is sent) and under the transport's ``buffer_updated`` (the answer, the sample),
nothing else the event loop does meanwhile. The north walk hands one such scan (one sample) to
:meth:`North.deliver` of a runtime with every face (not started: nothing is sent or served,
each face takes the scan as it would): JSON lines on stdout, the MQTT sink (it queues), the
OPC UA server (it keeps the sample for its applying task), the Modbus register image, the web
console's state and the metrics endpoint.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from types import CodeType, FrameType
from typing import Any

__all__ = ["Walk", "figure", "main", "north_walk", "request_walk"]

PACKAGE = Path(__file__).resolve().parent.parent


class Walk:
    """Records the plcstack functions entered under the root functions while armed."""

    def __init__(self, roots: set[CodeType]) -> None:
        self.roots = roots
        self.depth = 0
        self.order: list[str] = []
        self.calls: dict[str, int] = {}

    def _hook(self, frame: FrameType, event: str, arg: Any) -> None:
        if event == "call":
            code = frame.f_code
            if self.depth == 0 and code not in self.roots:
                return
            self.depth += 1
            name = _name(code)
            if name is not None:
                if name not in self.calls:
                    self.order.append(name)
                    self.calls[name] = 0
                self.calls[name] += 1
        elif event == "return" and self.depth:
            self.depth -= 1

    def arm(self) -> None:
        sys.setprofile(self._hook)

    def disarm(self) -> None:
        sys.setprofile(None)

    def lines(self) -> list[str]:
        """One line per function, in the order first entered: its file, its name, its calls."""
        return [f"{name}{f'  x{n}' if (n := self.calls[name]) > 1 else ''}" for name in self.order]

    def files(self) -> list[str]:
        return list(dict.fromkeys(name.split(" ")[0] for name in self.order))


def _name(code: CodeType) -> str | None:
    """``poll/scanner.py Scanner._fire`` for a plcstack function (this module's excluded)."""
    try:
        path = Path(code.co_filename).resolve().relative_to(PACKAGE)
    except ValueError:
        return None
    if path.parts[:2] == ("bench", "walk.py"):
        return None
    return f"{path.as_posix()} {code.co_qualname}"


async def _responder() -> tuple[asyncio.Server, int]:
    """An E71 that answers every 01H read of 64 words with the same normal answer."""
    answer = b"\x81\x00" + bytes(128)

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                await reader.readexactly(12)
                writer.write(answer)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    return server, server.sockets[0].getsockname()[1]


def _config(port: int) -> Any:
    from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
    from plcstack.values import RAW

    tag = TagConfig("w", "D0", RAW, 64, "default", modbus="hr:0")
    return PollConfig((PlcConfig("plc", f"e71+tcp://127.0.0.1:{port}", (tag,)),), {"default": 0.05})


async def _request_walk() -> Walk:
    from plcstack.poll.engine import Poller
    from plcstack.poll.ticker import Ticker
    from plcstack.transports import tcp

    server, port = await _responder()
    try:
        async with Poller(_config(port)) as poller:
            seen = 0
            async for batch in poller.batches():  # the first read is checked, then prepared
                seen += len(batch)
                if seen >= 3:
                    break
            # the ticker's callback, and the TCP protocol's receive step (by name: it is the
            # transport's own class)
            answer = vars(tcp)["_TcpProtocol"].buffer_updated.__code__
            walk = Walk({Ticker._fire.__code__, answer})
            walk.arm()
            try:
                async for _batch in poller.batches():
                    break
            finally:
                walk.disarm()
    finally:
        server.close()
        await server.wait_closed()
    return walk


def request_walk() -> Walk:
    """The walk of one polled read (see the module's docstring)."""
    return asyncio.run(_request_walk())


def north_walk() -> Walk:
    """The walk of one scan's sample through :meth:`North.deliver` (see the module's docstring)."""
    from plcstack.north.config import NorthConfig
    from plcstack.north.metrics import MetricsSettings
    from plcstack.north.modbus.config import ModbusSettings
    from plcstack.north.mqtt import parse_mqtt
    from plcstack.north.opcua_config import OpcUaConfig
    from plcstack.north.pipeline import North
    from plcstack.north.stdout import StdoutLines
    from plcstack.north.web.settings import WebSettings
    from plcstack.poll.engine import Poller
    from plcstack.poll.samples import Quality, Scan, make_sample
    from plcstack.poll.sinks import jsonl_text

    async def run() -> Walk:
        poller = Poller(_config(1))
        stdout = StdoutLines(jsonl_text(poller.config.plcs), io.StringIO())
        every = NorthConfig(
            mqtt=parse_mqtt({"url": "mqtt://127.0.0.1:1"}),
            opcua=OpcUaConfig(endpoint="opc.tcp://127.0.0.1:0/plcstack"),
            modbus=ModbusSettings(port=0),
            web=WebSettings(port=0),
            metrics=MetricsSettings(port=0),
        )
        north = North(poller, every, faces=[stdout])
        sample = make_sample("plc", "w", [0] * 64, Quality.GOOD, 1.0, 1.001, None)
        scan = Scan("plc", "default", 1.0, 1.001, (sample,))
        north.deliver([scan])  # once untraced: first-use work is not the path
        walk = Walk({North.deliver.__code__})
        walk.arm()
        try:
            north.deliver([scan])
        finally:
            walk.disarm()
        for client in (poller.client(name) for name in poller.plcs):
            client.transport.abort()
        return walk

    return asyncio.run(run())


def figure(walk: Walk, title: str) -> str:
    """The figure of one walk, as ARCHITECTURE.md shows it."""
    lines = walk.lines()
    files = walk.files()
    calls = sum(walk.calls.values())
    head = f"{title}: {len(lines)} functions entered ({calls} calls), {len(files)} files"
    return "\n".join(["```", head, "", *lines, "```"])


def figures() -> dict[str, str]:
    return {
        "request": figure(request_walk(), "one polled E71 read (scan due -> scan queued)"),
        "north": figure(north_walk(), "one scan's sample through the runtime to every face"),
    }


def replace_figures(text: str, found: dict[str, str]) -> str:
    """``text`` with the blocks between the ``walk:NAME`` markers replaced."""
    for name, block in found.items():
        begin, end = f"<!-- walk:{name}:begin -->\n", f"<!-- walk:{name}:end -->"
        match = re.search(re.escape(begin) + r"(?:.*?\n)?" + re.escape(end), text, re.S)
        if match is None:
            raise ValueError(f"no walk:{name} markers")
        text = text[: match.start()] + begin + block + "\n" + end + text[match.end() :]
    return text


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m plcstack.bench.walk")
    parser.add_argument("--write", metavar="FILE", help="replace the figures in FILE")
    args = parser.parse_args(argv)
    found = figures()
    if args.write:
        path = Path(args.write)
        path.write_text(replace_figures(path.read_text(encoding="utf-8"), found), encoding="utf-8")
    else:
        print("\n\n".join(found.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
