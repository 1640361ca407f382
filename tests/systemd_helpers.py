"""A stand-in for systemd's side of the notify protocol: a Unix datagram socket that records
every message with the time it arrived.

It receives in a thread of its own, so the arrival times are true even while the event loop of
the process under test is blocked (the watchdog test blocks it on purpose). Each datagram is
stamped with the time the kernel queued it (``SO_TIMESTAMP``), not the time the thread got to
read it: on a loaded machine the thread (which needs the GIL the loop holds) read two pings
sent 150 ms apart in one go, 300 ms after the one before, and a correct ping schedule failed.
Bound to a file path, or with ``abstract=True`` to a name in Linux's abstract namespace
(``NOTIFY_SOCKET=@name``), as systemd may hand either.
"""

from __future__ import annotations

import asyncio
import os
import socket
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Self

from tests.ports import free_port

__all__ = ["Message", "NotifySocket", "two_plcs"]

#: Linux's SO_TIMESTAMP (asm-generic/socket.h), which Python's socket module does not name
SO_TIMESTAMP = getattr(socket, "SO_TIMESTAMP", 29)


@dataclass(frozen=True)
class Message:
    """One datagram: its assignments in order, and when it arrived (``time.monotonic``)."""

    at: float
    fields: tuple[tuple[str, str], ...]

    def get(self, name: str) -> str | None:
        return next((value for key, value in self.fields if key == name), None)

    @property
    def names(self) -> list[str]:
        return [key for key, _ in self.fields]


class NotifySocket:
    """``with NotifySocket(tmp_path) as sock: env["NOTIFY_SOCKET"] = sock.address``."""

    def __init__(self, directory: Path, *, abstract: bool = False) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        if abstract:
            name = f"plcstack-test-notify-{os.getpid()}-{id(self)}"
            self.sock.bind(b"\0" + name.encode())
            self.address = "@" + name
        else:
            path = directory / "notify.sock"
            self.sock.bind(str(path))
            self.address = str(path)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMP, 1)
        self.sock.settimeout(0.05)
        self.messages: list[Message] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        while not self._stop.is_set():
            try:
                data, ancillary, _, _ = self.sock.recvmsg(65536, socket.CMSG_SPACE(16))
            except TimeoutError:
                continue
            except OSError:
                return
            # the wall clock first: a thread preempted between the two reads then puts the
            # arrival a little late, never before the sender's own monotonic stamp (read in the
            # other order, a 14 us preemption put a RELOADING=1 before its MONOTONIC_USEC)
            wall = time.time()
            at = time.monotonic()
            for level, kind, stamp in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMP:
                    seconds, micros = struct.unpack("@ll", stamp[: struct.calcsize("@ll")])
                    # the kernel's wall-clock stamp, on the monotonic clock the tests use
                    at -= wall - (seconds + micros / 1e6)
            fields = tuple(
                (name, value)
                for line in data.decode().split("\n")
                if line
                for name, _, value in [line.partition("=")]
            )
            with self._lock:
                self.messages.append(Message(at, fields))

    def received(self) -> list[Message]:
        with self._lock:
            return list(self.messages)

    def with_field(self, name: str) -> list[Message]:
        return [m for m in self.received() if m.get(name) is not None]

    async def count(self, name: str, n: int, timeout: float = 5.0) -> list[Message]:
        """The messages with ``name`` once ``n`` of them have arrived (the receiving thread may
        be a moment behind the sender)."""
        deadline = time.monotonic() + timeout
        while len(got := self.with_field(name)) < n:
            if time.monotonic() > deadline:
                raise AssertionError(f"{len(got)} of {n} {name} messages within {timeout} s")
            await asyncio.sleep(0.01)
        return got

    def _first(self, name: str, value: str | None, after: float) -> Message | None:
        for m in self.received():
            got = m.get(name)
            if m.at >= after and got is not None and (value is None or got == value):
                return m
        return None

    def _missing(self, name: str, value: str | None, timeout: float) -> AssertionError:
        return AssertionError(
            f"no {name}{'=' + value if value else ''} within {timeout} s;"
            f" received: {[m.fields for m in self.received()]}"
        )

    def wait_for(
        self, name: str, value: str | None = None, *, after: float = 0.0, timeout: float = 10.0
    ) -> Message:
        """The first message that arrived at or after ``after`` with ``name`` (equal to
        ``value``, if given), waiting for it up to ``timeout`` seconds (blocking)."""
        deadline = time.monotonic() + timeout
        while (m := self._first(name, value, after)) is None:
            if time.monotonic() > deadline:
                raise self._missing(name, value, timeout)
            time.sleep(0.01)
        return m

    async def arrival(
        self, name: str, value: str | None = None, *, after: float = 0.0, timeout: float = 10.0
    ) -> Message:
        """:meth:`wait_for` for a test on an event loop (it sleeps on the loop)."""
        deadline = time.monotonic() + timeout
        while (m := self._first(name, value, after)) is None:
            if time.monotonic() > deadline:
                raise self._missing(name, value, timeout)
            await asyncio.sleep(0.01)
        return m

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()
        if not self.address.startswith("@"):
            Path(self.address).unlink(missing_ok=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def two_plcs(directory: Path, url: str, interval: float) -> Path:
    """``plant.toml`` in ``directory``: ``press1`` at ``url`` (a simulator that answers) and
    ``oven2`` on a port where nothing listens, both scanned every ``interval`` seconds."""
    config = directory / "plant.toml"
    config.write_text(
        f"[poll]\ninterval = {interval}\n"
        f'[[plc]]\nname = "press1"\nurl = "{url}"\n[plc.tags]\nx = {{ address = "D0" }}\n'
        f'[[plc]]\nname = "oven2"\nurl = "e71+tcp://127.0.0.1:{free_port()}"\n'
        '[plc.tags]\ny = { address = "D0" }\n'
    )
    return config
