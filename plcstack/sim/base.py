"""What every simulator offers to in-process users (tests, the demo, the benchmarks).

Each ``plcstack.sim.NAME`` module has ``async def start(...) -> Simulator`` that binds (port 0 picks
a free port) and returns once clients can connect. The object tells where it listens and the URL a
client should use, so callers never assemble URLs by hand.
"""

from __future__ import annotations

import asyncio
from abc import abstractmethod

from plcstack.resource import AsyncResource

__all__ = ["ConnectionCount", "Simulator", "TcpSimulator", "UdpSimulator"]


class ConnectionCount:
    """How many client connections a simulator holds now, and the most it ever held at once.

    The scale-out tests read ``peak`` to prove that no PLC ever had two pollers at once.
    """

    __slots__ = ("current", "peak", "total")

    def __init__(self) -> None:
        self.current = 0
        self.peak = 0
        self.total = 0

    def opened(self) -> None:
        self.current += 1
        self.total += 1
        self.peak = max(self.peak, self.current)

    def closed(self) -> None:
        self.current -= 1


class Simulator(AsyncResource):
    """A running simulator. Close it with ``await sim.aclose()`` or ``async with``."""

    #: the URL a plcstack client uses to reach this simulator, e.g. ``e71+tcp://127.0.0.1:40001``
    url: str

    @abstractmethod
    async def aclose(self) -> None: ...

    async def serve_forever(self) -> None:
        """Serve until cancelled (the CLI's ``plcstack sim``)."""
        try:
            await asyncio.Event().wait()
        finally:
            await self.aclose()


class TcpSimulator(Simulator):
    """A simulator behind one ``asyncio.Server``; ``host``/``port`` are the bound address."""

    def __init__(self, server: asyncio.Server, scheme: str, query: str = "") -> None:
        self.server = server
        sockname = server.sockets[0].getsockname()
        self.host: str = sockname[0]
        self.port: int = sockname[1]
        self.url = f"{scheme}://{self.host}:{self.port}" + (f"?{query}" if query else "")
        self._conn_tasks: set[asyncio.Task[None]] = set()
        #: client connections now / at most at once (simulators without per-connection tasks
        #: call ``opened``/``closed`` themselves)
        self.connection_count = ConnectionCount()

    def track(self, task: asyncio.Task[None]) -> None:
        """Remember a per-connection task so ``aclose`` can end it (no task outlives the sim);
        the connection counts as open until the task ends."""
        self._conn_tasks.add(task)
        self.connection_count.opened()
        task.add_done_callback(self._untrack)

    def _untrack(self, task: asyncio.Task[None]) -> None:
        self._conn_tasks.discard(task)
        self.connection_count.closed()

    async def aclose(self) -> None:
        self.server.close()
        for task in list(self._conn_tasks):
            task.cancel()
        if self._conn_tasks:
            await asyncio.gather(*self._conn_tasks, return_exceptions=True)
        await self.server.wait_closed()


class UdpSimulator(Simulator):
    """A simulator on one bound UDP socket (``asyncio.DatagramTransport``); replies go to the
    datagram's source address. ``host``/``port`` are the bound address."""

    def __init__(self, transport: asyncio.DatagramTransport, scheme: str, query: str = "") -> None:
        self.transport = transport
        sockname = transport.get_extra_info("sockname")
        self.host: str = sockname[0]
        self.port: int = sockname[1]
        self.url = f"{scheme}://{self.host}:{self.port}" + (f"?{query}" if query else "")

    async def aclose(self) -> None:
        self.transport.close()
