"""Issue 16's fast paths decide exactly as the general paths they shortcut.

* The check for unsolicited bytes before a request: the general path lets the event loop run
  once; the fast path asks the kernel (FIONREAD) and skips that pass when nothing waits. Both must
  find stale bytes wherever they are (already delivered, or still in the kernel) and never return
  a stale answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
from typing import Any

import pytest

from plcstack.transports.tcp import TcpTransport
from tests.test_client_base import LineClient


class _StaleServer:
    """Answers "ASK n" with "n"; ``extra`` bytes follow the answer to ``extra_after`` (a
    duplicated or confused answer), ``delay`` seconds later. Runs in threads, not on the test's event loop,
    so that it sends while the loop is blocked (bytes that reach the kernel, not the client)."""

    def __init__(self) -> None:
        self.connections = 0
        self.extra = b""
        self.extra_after = b""
        self.delay = 0.0
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                conn, _ = self.listener.accept()
                self.connections += 1
                threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError), conn.makefile("rb") as lines:
            for line in lines:
                answer = line.split()[-1]
                conn.sendall(answer + b"\n")
                if self.extra and answer == self.extra_after:
                    time.sleep(self.delay)
                    conn.sendall(self.extra)


@pytest.fixture
def stale_server() -> Any:
    srv = _StaleServer()
    yield srv
    srv.listener.close()


async def test_input_waiting_sees_bytes_the_loop_has_not_read(stale_server: Any) -> None:
    transport = TcpTransport("127.0.0.1", stale_server.port)
    await transport.open(1.0)
    try:
        transport.write(b"ASK 1\n")
        assert await transport.read() == b"1\n"
        assert not transport.input_waiting()  # nothing in the kernel, nothing delivered
        transport.write(b"ASK 2\n")
        time.sleep(0.2)  # blocks the loop: the answer reaches the kernel, not the protocol
        assert transport.input_waiting()
        assert transport.take_received() == []
        await asyncio.sleep(0.05)  # the loop reads it now
        assert not transport.input_waiting()
        assert transport.take_received() == [b"2\n"]
    finally:
        transport.abort()
    assert transport.input_waiting()  # closed: "cannot tell", the general path


@pytest.mark.parametrize("general", [False, True], ids=["fast", "general"])
@pytest.mark.parametrize("where", ["delivered", "in-kernel"])
async def test_stale_bytes_are_found_on_both_paths(
    stale_server: Any, general: bool, where: str
) -> None:
    client = LineClient(
        f"line://127.0.0.1:{stale_server.port}", TcpTransport("127.0.0.1", stale_server.port)
    )
    client.stale_check_needs_loop_pass = general
    async with client:
        assert await client.read("ASK 1") == [1]
        stale_server.extra = b"77\n"  # a second answer to "ASK 2", 20 ms late
        stale_server.extra_after = b"2"
        stale_server.delay = 0.02
        assert await client.read("ASK 2") == [2]
        if where == "delivered":
            await asyncio.sleep(0.2)  # the loop has read the stale answer into the protocol
        else:
            time.sleep(0.2)  # the stale answer sits in the kernel; the loop has not run
        # never 77: the stale answer is found, the connection replaced, the request sent anew
        assert await client.read("ASK 3") == [3]
        assert client.stats.errors == 1
        assert stale_server.connections == 2
        assert await client.read("ASK 4") == [4]
        assert stale_server.connections == 2


@pytest.mark.parametrize("general", [False, True], ids=["fast", "general"])
async def test_clean_requests_are_the_same_on_both_paths(stale_server: Any, general: bool) -> None:
    client = LineClient(
        f"line://127.0.0.1:{stale_server.port}", TcpTransport("127.0.0.1", stale_server.port)
    )
    client.stale_check_needs_loop_pass = general
    async with client:
        assert [await client.read(f"ASK {i}") for i in range(20)] == [[i] for i in range(20)]
        assert client.stats.errors == 0 and client.stats.requests == 20
    assert stale_server.connections == 1
