"""Replay a capture: serve what a pcapng (or pcap) file recorded, as the PLCs answered then.

``plcstack sim replay FILE`` listens once for every server the capture holds (each TCP or UDP
server address, each AS511 line) and answers each request with the answer recorded for it
(matched by the request's bytes, in order: :mod:`plcstack.wire.script`), so a failure
recorded in the field becomes a test: poll the replay and see what the poller made of it.

A request the capture does not hold is not guessed at: the replay logs it once (WARNING, with
its bytes, the nearest recorded request and the byte where they differ), closes that
connection (UDP: answers nothing) so the client reports it at once, and counts it. When the
recorded exchanges are used up it starts again from the first, said once (INFO), unless
``--once``. ``--timing`` answers after the delay recorded for each answer.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plcstack.sim.base import (
    DEFAULT_IDLE_TIMEOUT,
    DEFAULT_MAX_CONNECTIONS,
    Simulator,
    add_guard_arguments,
    close_writer,
    limits_of,
    module_guard,
)
from plcstack.transports import tap
from plcstack.transports.guard import FRAME_TIMEOUT, FaceGuard, FrameDeadline, Limits, earliest
from plcstack.transports.peer import peer_address
from plcstack.wire.script import Match, Script
from plcstack.wire.streams import Conversation, conversations, exchanges

__all__ = [
    "Recorded",
    "ReplaySimulator",
    "add_cli_arguments",
    "recorded_servers",
    "serve_cli",
    "start",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Recorded:
    """One server of a capture: its kind, its recorded address (or serial device), its
    exchanges in capture order."""

    kind: str
    server: str
    conversations: tuple[Conversation, ...]

    @property
    def name(self) -> str:
        return f"{self.server} ({self.kind.upper()})" if self.kind != "serial" else self.server

    def script(self, repeat: bool) -> Script:
        recorded = sorted(
            (e for c in self.conversations for e in exchanges(c)), key=lambda e: e.nanos
        )
        return Script(self.name, recorded, repeat=repeat)


def recorded_servers(capture: bytes) -> list[Recorded]:
    """The servers of a capture, in the order they first appear."""
    grouped: dict[tuple[str, str], list[Conversation]] = {}
    for conversation in conversations(capture):
        if any(c.from_client for c in conversation.chunks):
            grouped.setdefault((conversation.kind, conversation.server), []).append(conversation)
    return [Recorded(kind, server, tuple(convs)) for (kind, server), convs in grouped.items()]


def _port_of(server: str) -> int:
    return int(server.rsplit(":", 1)[1])


class _Replayer:
    """One server being replayed: its script, its guard (the limits of every simulator; a
    request not in the capture is said once per host per burst with its bytes), what to log."""

    def __init__(self, recorded: Recorded, *, repeat: bool, timing: bool, guard: FaceGuard) -> None:
        self.recorded = recorded
        self.script = recorded.script(repeat)
        self.timing = timing
        self.guard = guard
        self._rounds_said = 1

    def decide(self, data: bytes, peer: str, host: str | None = None) -> Match:
        match = self.script.match(data)
        if self.script.rounds > self._rounds_said:
            self._rounds_said = self.script.rounds
            if self._rounds_said == 2:
                log.info(
                    "replay of %s: every recorded exchange answered; starting again from the "
                    "first (said once)",
                    self.recorded.name,
                )
        if match.kind == "mismatch":
            self.guard.malformed(
                peer,
                host,
                f"a request that is not in the capture: {data[:64].hex(' ')}; the nearest"
                f" recorded request {match.nearest[:64].hex(' ')} differs at byte"
                f" {match.differs_at}; no answer, the connection is closed",
            )
        return match

    async def delay(self, match: Match) -> None:
        if self.timing and match.exchange is not None and match.exchange.delay > 0:
            await asyncio.sleep(match.exchange.delay)


class ReplaySimulator(Simulator):
    """Every replayed server of one capture; ``urls`` says where each listens."""

    def __init__(self) -> None:
        self.url = ""
        #: recorded server name -> where the replay serves it (host:port, or the pty path)
        self.listening: dict[str, str] = {}
        self._replayers: list[_Replayer] = []
        self._servers: list[asyncio.Server] = []
        self._udp: list[asyncio.DatagramTransport] = []
        self._ptys: list[_PtyLine] = []
        self._tasks: set[asyncio.Task[None]] = set()

    @property
    def scripts(self) -> dict[str, Script]:
        return {r.recorded.name: r.script for r in self._replayers}

    @property
    def guards(self) -> dict[str, FaceGuard]:
        """The guard of each replayed server, by its recorded name (what it refused, closed,
        and the requests not in the capture, as ``malformed``)."""
        return {r.recorded.name: r.guard for r in self._replayers}

    @property
    def mismatches(self) -> int:
        return sum(r.script.mismatches for r in self._replayers)

    async def aclose(self) -> None:
        for server in self._servers:
            server.close()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        for server in self._servers:
            await server.wait_closed()
        for transport in self._udp:
            transport.close()
        for line in self._ptys:
            line.close()
        for replayer in self._replayers:
            replayer.guard.close()  # the counts of bursts not said yet
            if replayer.script.mismatches:
                log.warning(
                    "replay of %s: %d request(s) were not in the capture",
                    replayer.recorded.name,
                    replayer.script.mismatches,
                )

    # -- TCP -------------------------------------------------------------------------------
    async def _serve_tcp(self, replayer: _Replayer, host: str, port: int) -> str:
        guard = replayer.guard

        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            visit = guard.admit(writer.get_extra_info("peername"))
            if visit is None:  # a cap refused it (counted and said)
                writer.transport.abort()
                return
            task = asyncio.current_task()
            if task is not None:
                self._tasks.add(task)
            pending = b""
            # a request begun must be complete within FRAME_TIMEOUT of its first byte: the
            # idle deadline restarts with every byte, so a trickle would hold a slot for ever
            frame = FrameDeadline(FRAME_TIMEOUT)
            try:
                while True:
                    due = frame.due
                    try:
                        async with asyncio.timeout_at(earliest(visit.due, due)):
                            data = await reader.read(65536)
                    except TimeoutError:
                        if due is not None and asyncio.get_running_loop().time() >= due:
                            visit.frame_late()
                            return
                        if visit.expired() is not None:
                            return
                        continue
                    if not data:
                        return
                    visit.touch()
                    pending += data
                    while pending:
                        match = replayer.decide(pending, visit.peer, visit.host)
                        if match.kind == "wait":
                            break
                        if match.kind == "mismatch" or match.exchange is None:
                            return
                        visit.served()
                        await replayer.delay(match)
                        writer.write(b"".join(match.answers))
                        await writer.drain()
                        pending = pending[match.taken :]
                    frame.note(bool(pending))
            except (ConnectionError, OSError, asyncio.CancelledError):
                return
            finally:
                visit.leave()
                frame.cancel()
                if task is not None:
                    self._tasks.discard(task)
                await close_writer(writer)

        server = await tap.start_server(handle, host, port)
        self._servers.append(server)
        return peer_address(server.sockets[0].getsockname()) or f"{host}:{port}"

    # -- UDP -------------------------------------------------------------------------------
    async def _serve_udp(self, replayer: _Replayer, host: str, port: int) -> str:
        owner = self

        class Endpoint(asyncio.DatagramProtocol):
            transport: asyncio.DatagramTransport | None = None

            def connection_made(self, transport: asyncio.BaseTransport) -> None:
                self.transport = transport  # type: ignore[assignment]

            def datagram_received(self, data: bytes, addr: Any) -> None:
                match = replayer.decide(data, peer_address(addr) or "?", str(addr[0]))
                if match.kind != "answer" or match.exchange is None:
                    return
                delay = match.exchange.delay
                if replayer.timing and delay > 0:
                    later = self._later(delay, match.answers, addr)
                    task = asyncio.get_running_loop().create_task(later)
                    owner._tasks.add(task)
                    task.add_done_callback(owner._tasks.discard)
                else:
                    self._send(match.answers, addr)

            async def _later(self, delay: float, answers: tuple[bytes, ...], addr: Any) -> None:
                await asyncio.sleep(delay)
                self._send(answers, addr)

            def _send(self, answers: tuple[bytes, ...], addr: Any) -> None:
                if self.transport is not None and not self.transport.is_closing():
                    for answer in answers:
                        self.transport.sendto(answer, addr)

        transport, _ = await tap.create_datagram_endpoint(Endpoint, local_addr=(host, port))
        self._udp.append(transport)
        return peer_address(transport.get_extra_info("sockname")) or f"{host}:{port}"


class _PtyLine:
    """An AS511 line replayed on a new pseudo-terminal; the PG opens :attr:`path`."""

    def __init__(self, replayer: _Replayer, owner: ReplaySimulator) -> None:
        import tty  # POSIX only

        self.replayer = replayer
        self.owner = owner
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self._pending = b""
        self._out = bytearray()
        self._busy = False
        loop = asyncio.get_running_loop()
        loop.add_reader(self._master, self._readable)

    def _readable(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except OSError:
            return  # EIO while no PG has the port open; nothing to read
        if not data:
            return
        self._pending += data
        if not self._busy:
            self._busy = True
            task = asyncio.get_running_loop().create_task(self._answer())
            self.owner._tasks.add(task)
            task.add_done_callback(self.owner._tasks.discard)

    async def _answer(self) -> None:
        try:
            while self._pending:
                match = self.replayer.decide(self._pending, self.path, self.path)
                if match.kind == "wait":
                    return
                if match.kind == "mismatch" or match.exchange is None:
                    self._pending = b""  # a line cannot be closed: the PG times out
                    return
                await self.replayer.delay(match)
                self._pending = self._pending[match.taken :]
                self._write(b"".join(match.answers))
        finally:
            self._busy = False

    def _write(self, data: bytes) -> None:
        self._out += data
        self._flush()

    def _flush(self) -> None:
        loop = asyncio.get_running_loop()
        while self._out:
            try:
                n = os.write(self._master, self._out)
            except BlockingIOError:
                loop.add_writer(self._master, self._flush)
                return
            except OSError:
                self._out.clear()
                break
            del self._out[:n]
        loop.remove_writer(self._master)

    def close(self) -> None:
        loop = asyncio.get_running_loop()
        loop.remove_reader(self._master)
        loop.remove_writer(self._master)
        os.close(self._master)
        os.close(self._slave)


async def start(
    capture: str | Path | bytes,
    *,
    host: str = "127.0.0.1",
    same_ports: bool = False,
    port: int | None = None,
    servers: list[str] | None = None,
    repeat: bool = True,
    timing: bool = False,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    limits: Limits | None = None,
) -> ReplaySimulator:
    """Replay the servers of ``capture`` (a file, or its bytes); returns once each listens.

    ``same_ports`` binds each TCP/UDP server on its recorded port (on ``host``), else on a
    free one; ``port`` binds the one server of the replay there (``ValueError`` when there
    are several: choose one with ``servers``); ``servers`` limits the replay to these
    recorded servers (names as :attr:`Recorded.name` or their address). Each TCP server is
    guarded as every simulator is (:func:`~plcstack.sim.base.module_guard`): 16 connections
    from any host, a first request within 10 s, ``idle_timeout``; ``limits`` replaces them.
    Raises
    ``ValueError`` for a file that holds no conversation to replay, ``OSError`` for one that
    cannot be read or a port in use.
    """
    data = (
        capture if isinstance(capture, bytes) else await asyncio.to_thread(Path(capture).read_bytes)
    )
    found = recorded_servers(data)
    if servers:
        wanted = set(servers)
        found = [r for r in found if r.name in wanted or r.server in wanted]
        missing = wanted - {r.name for r in found} - {r.server for r in found}
        if missing:
            raise ValueError(f"the capture has no server {', '.join(sorted(missing))}")
    if not found:
        raise ValueError("the capture holds no TCP, UDP or AS511 conversation to replay")
    if port is not None and len(found) != 1:
        names = ", ".join(r.name for r in found)
        raise ValueError(f"--port serves one server; the capture has {len(found)}: {names}")
    sim = ReplaySimulator()
    try:
        for recorded in found:
            guard = module_guard(
                "replay",
                f"replay of {recorded.name}",
                DEFAULT_MAX_CONNECTIONS,
                idle_timeout,
                limits,
                logger=log,
            )
            replayer = _Replayer(recorded, repeat=repeat, timing=timing, guard=guard)
            sim._replayers.append(replayer)
            bind = port if port is not None else 0
            if same_ports and recorded.kind != "serial":
                bind = _port_of(recorded.server)
            if recorded.kind == "tcp":
                where = await sim._serve_tcp(replayer, host, bind)
                guard.announce(where)
            elif recorded.kind == "udp":
                where = await sim._serve_udp(replayer, host, bind)
            else:
                line = _PtyLine(replayer, sim)
                sim._ptys.append(line)
                where = line.path
            sim.listening[recorded.name] = where
    except BaseException:
        await sim.aclose()
        raise
    first = found[0]
    sim.url = sim.listening[first.name]
    return sim


# -- CLI: plcstack sim replay ------------------------------------------------------------------


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", metavar="FILE", help="a pcapng or pcap capture to replay")
    parser.add_argument(
        "--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)"
    )
    parser.add_argument(
        "--same-ports",
        action="store_true",
        help="serve each server on its recorded port (default: any free port, printed)",
    )
    parser.add_argument(
        "--port",
        type=int,
        default=None,
        help="serve the capture's one server on this port (default: any free port, printed)",
    )
    parser.add_argument(
        "--server",
        action="append",
        metavar="ADDRESS",
        help="replay only this recorded server (HOST:PORT or the serial device; repeatable)",
    )
    parser.add_argument(
        "--once",
        action="store_true",
        help="do not start again when the recorded exchanges are used up (default: repeat)",
    )
    parser.add_argument(
        "--timing", action="store_true", help="answer after the delay recorded for each answer"
    )
    add_guard_arguments(parser, DEFAULT_MAX_CONNECTIONS)


async def serve_cli(args: argparse.Namespace, announce: Callable[[str], None]) -> None:
    sim = await start(
        args.capture,
        host=args.host,
        same_ports=args.same_ports,
        port=args.port,
        servers=args.server,
        repeat=not args.once,
        timing=args.timing,
        limits=limits_of(args),
    )
    for name, where in sim.listening.items():
        exchanges_ = len(sim.scripts[name].exchanges)
        kind = "serial port" if where.startswith("/") else "listening on"
        suffix = "" if where.startswith("/") else (" (UDP)" if name.endswith("(UDP)") else " (TCP)")
        announce(f"{kind} {where}{suffix}, replaying {name}: {exchanges_} exchanges")
    await sim.serve_forever()
