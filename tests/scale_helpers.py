"""Tools of the scale-out tests: a fleet of E71 simulators that records who polled when, a TCP
proxy that can be cut (a worker loses one server but nothing else), and worker processes."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from plcstack.sim import e71
from tests.aio_helpers import ends_quietly

__all__ = ["CutProxy", "Fleet", "WorkerProcess"]

REPO = Path(__file__).resolve().parent.parent


@dataclass
class _Watch:
    sim: e71.E71TcpSimulator
    last_requests: int = 0
    last_connects: int = 0
    #: loop times at which new requests were seen (sampled every ``Fleet.every`` seconds)
    seen: list[float] = field(default_factory=list)
    #: new connections seen, each as the sample before and the sample that saw it: the
    #: connection opened somewhere between the two
    connects: list[tuple[float, float]] = field(default_factory=list)


class Fleet:
    """``count`` E71 simulators (8 connections each, so a second poller would be accepted and
    counted, not refused) and a watcher that samples their request counters."""

    def __init__(self, count: int, *, interval: float, every: float = 0.02) -> None:
        self.count = count
        self.interval = interval
        self.every = every
        self.watch: dict[str, _Watch] = {}
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> Fleet:
        for i in range(self.count):
            sim = await e71.start()
            assert isinstance(sim, e71.E71TcpSimulator)
            self.watch[f"plc{i:02d}"] = _Watch(sim)
        self._task = asyncio.get_running_loop().create_task(self._sample())
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        for w in self.watch.values():
            await w.sim.aclose()

    async def _sample(self) -> None:
        loop = asyncio.get_running_loop()
        now = loop.time()
        while True:
            before, now = now, loop.time()
            for w in self.watch.values():
                if w.sim.requests != w.last_requests:
                    w.last_requests = w.sim.requests
                    w.seen.append(now)
                total = w.sim.connection_count.total
                if total != w.last_connects:
                    w.last_connects = total
                    w.connects.append((before, now))
            await asyncio.sleep(self.every)

    def toml(self, path: Path, *, timeout: float = 0.5) -> Path:
        lines = [
            "[poll]",
            f"interval = {self.interval}",
            f"timeout = {timeout}",
            f"connect_timeout = {timeout}",
            "backoff_max = 0.2",
        ]
        for name, w in self.watch.items():
            lines += ["[[plc]]", f'name = "{name}"', f'url = "{w.sim.url}"']
            lines += ["[plc.tags]", 'x = "D0"']
        path.write_text("\n".join(lines) + "\n")
        return path

    def peaks(self) -> dict[str, int]:
        return {name: w.sim.connection_count.peak for name, w in self.watch.items()}

    def reset_peaks(self) -> None:
        """Start counting peaks anew (from the connections open now)."""
        for w in self.watch.values():
            count = w.sim.connection_count
            count.peak = count.current

    def polled_after(self, t: float) -> dict[str, float | None]:
        """For each PLC, the first time after ``t`` its simulator saw a request (or None)."""
        out: dict[str, float | None] = {}
        for name, w in self.watch.items():
            out[name] = next((s for s in w.seen if s > t), None)
        return out

    def requests(self) -> int:
        """Requests all simulators answered so far."""
        return sum(w.sim.requests for w in self.watch.values())

    def reconnected_after(self, t: float) -> dict[str, float | None]:
        """For each PLC, the first request seen on a connection opened after ``t`` (or None):
        the new owner's first poll, not a late request of the old one. A connection sampled
        after ``t`` but perhaps opened before it (the sample before was earlier than ``t``) is
        not one: the old owner reconnected just before ``t`` (under load, a request timed out)."""
        out: dict[str, float | None] = {}
        for name, w in self.watch.items():
            connect = next((c for b, c in w.connects if b >= t), None)
            if connect is None:
                out[name] = None
            else:
                out[name] = next((s for s in w.seen if s >= connect), None)
        return out

    def longest_gap(self, start: float, end: float) -> dict[str, float]:
        """For each PLC, the longest time in [start, end] without a request seen."""
        out: dict[str, float] = {}
        for name, w in self.watch.items():
            times = [start, *(s for s in w.seen if start < s < end), end]
            out[name] = max(b - a for a, b in itertools.pairwise(times))
        return out

    async def wait_all_polled(self, after: float, timeout: float) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while any(v is None for v in self.polled_after(after).values()):
            if loop.time() > deadline:
                missing = [k for k, v in self.polled_after(after).items() if v is None]
                raise AssertionError(f"not polled within {timeout} s: {missing}")
            await asyncio.sleep(0.05)


class CutProxy:
    """A TCP proxy on a free loopback port to ``host:port``. ``cut()`` closes every connection
    (each side sees the other go away) and refuses new ones until ``restore()``."""

    def __init__(self, host: str, port: int) -> None:
        self.target = (host, port)
        self.host = "127.0.0.1"
        self.port = 0
        self.open = True
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        self._server = await asyncio.start_server(ends_quietly(self._accept), self.host, 0)
        self.port = self._server.sockets[0].getsockname()[1]

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self.open:
            writer.transport.abort()
            return
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.target)
        except OSError:
            writer.transport.abort()
            return
        self._writers |= {writer, up_writer}
        await asyncio.gather(
            self._copy(reader, up_writer), self._copy(up_reader, writer), return_exceptions=True
        )

    async def _copy(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        finally:
            writer.transport.abort()
            self._writers.discard(writer)

    def cut(self) -> None:
        self.open = False
        for writer in list(self._writers):
            writer.transport.abort()
        self._writers.clear()

    def restore(self) -> None:
        self.open = True

    async def aclose(self) -> None:
        self.cut()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()


class WorkerProcess:
    """``plcstack poll CONFIG --mqtt ... --nats ...`` as a child process (stderr kept in a file)."""

    def __init__(
        self,
        name: str,
        config: Path,
        *,
        mqtt: str,
        nats: str | None,
        ttl: float,
        retry: float,
        keepalive: int = 2,
        logdir: Path,
    ) -> None:
        self.name = name
        self.log = logdir / f"{name}.log"
        self.command = [
            sys.executable,
            "-m",
            "plcstack",
            "poll",
            str(config),
            "--mqtt",
            mqtt,
            "--worker-id",
            name,
            "--lease-ttl",
            str(ttl),
            "--lease-retry",
            str(retry),
            "--keepalive",
            str(keepalive),
        ]
        if nats is not None:
            self.command += ["--nats", nats]
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        env = dict(os.environ, PYTHONPATH=str(REPO))
        with open(self.log, "ab") as err:
            self.proc = subprocess.Popen(
                self.command,
                stdout=subprocess.DEVNULL,
                stderr=err,
                stdin=subprocess.DEVNULL,
                env=env,
                cwd=REPO,
            )

    def kill(self) -> None:
        """``kill -9``: no handover, no clean disconnect; the kernel closes its sockets."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=5)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.kill()

    def text(self) -> str:
        try:
            return self.log.read_text(errors="replace")
        except OSError:
            return ""

    def cpu_seconds(self) -> float:
        """User + system CPU time of the process so far (Linux /proc)."""
        assert self.proc is not None
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        ticks = os.sysconf("SC_CLK_TCK")
        return (int(fields[11]) + int(fields[12])) / ticks


def now() -> float:
    return time.monotonic()
