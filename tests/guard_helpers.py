"""What the tests of every listening face share: a host that opens many idle sockets (from a
loopback address of its own, 127.0.0.2, so the per-host cap can tell it from the legitimate
client on 127.0.0.1), and the log lines a face's guard wrote."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import AsyncIterator

import pytest

__all__ = ["ATTACKER", "IDLE_SOCKETS", "guard_lines", "idle_sockets"]

#: the hostile host: any 127.x.y.z address reaches loopback
ATTACKER = "127.0.0.2"
#: sockets the hostile host opens, as in the issue
IDLE_SOCKETS = 64


@contextlib.asynccontextmanager
async def idle_sockets(
    port: int, count: int = IDLE_SOCKETS, source: str = ATTACKER, host: str = "127.0.0.1"
) -> AsyncIterator[list[socket.socket]]:
    """``count`` TCP connections to ``host:port`` from ``source`` that never send a byte
    (each connect completes: the kernel accepts before the face decides)."""
    loop = asyncio.get_running_loop()
    opened: list[socket.socket] = []
    try:
        for _ in range(count):
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setblocking(False)
            sock.bind((source, 0))
            opened.append(sock)
            await loop.sock_connect(sock, (host, port))
        yield opened
    finally:
        for sock in opened:
            sock.close()


def guard_lines(caplog: pytest.LogCaptureFixture, host: str = ATTACKER) -> list[str]:
    """The WARNING lines that name ``host``."""
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno >= logging.WARNING and host in r.getMessage()
    ]
