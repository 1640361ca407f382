"""A blocking facade for scripts and notebooks: the same async clients, run on an event loop in
a helper thread.

    import plcstack.sync
    from plcstack.values import KG

    with plcstack.sync.connect("s5lan://10.0.0.7:5010", timeout=3) as plc:
        words = plc.read("DB10.DW0", 4)      # list[int]
        level = plc.read_as("DB10.DW4", KG)  # float

Nothing is re-implemented: every call hands the client's coroutine to the loop thread through an
anyio :class:`~anyio.from_thread.BlockingPortal` (made for exactly this) and waits for it, so the
errors are the same :class:`~plcstack.errors.PlcError` subclasses, raised in the calling thread,
and the return types are the same. The facade is safe to use from several threads at once: the
calls meet on the one loop, where the client's single-flight lock orders them, as it does for
tasks. Each facade owns its loop thread; :meth:`SyncClient.close` (or leaving ``with``) closes
the connection and stops the thread.

The loop thread never holds the interpreter: it is a daemon thread with nothing that waits for it
at exit, so a script that forgets ``close()``, or ends with an exception, exits as it would
without plcstack (the operating system closes the connection).

Methods beyond ``read``/``write``/``read_as``/``write_as`` (``read_int32``, ``block_info``, ...)
are reached through :attr:`SyncClient.call`: ``plc.call(plc.client.read_int32, "D0", 2)``.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import threading
from collections.abc import Awaitable, Callable
from types import TracebackType
from typing import Any, Generic, Self, TypeVar, overload

import anyio
from anyio.from_thread import BlockingPortal

from plcstack.clients import connect as async_connect
from plcstack.clients.base import Client, Points
from plcstack.values import ValueType, WordOrder

__all__ = ["SyncClient", "connect"]

T = TypeVar("T")
R = TypeVar("R")
C = TypeVar("C", bound=Client)


class SyncClient(Generic[C]):
    """Blocking view of one async client ``client``, which runs on a helper thread's loop."""

    def __init__(self, client: C, portal: BlockingPortal, stop: Callable[[], None]) -> None:
        self.client = client
        self._portal = portal
        self._stop = stop
        self._closed = False
        self._close_lock = threading.Lock()

    @property
    def name(self) -> str:
        return self.client.name

    def __repr__(self) -> str:
        return f"<SyncClient {self.client!r}>"

    # -- calls ----------------------------------------------------------------------------------
    def call(self, func: Callable[..., Awaitable[R]], *args: Any) -> R:
        """Run ``await func(*args)`` on the client's loop and return its result (or raise its
        error) in this thread."""
        return self._portal.call(func, *args)

    def open(self) -> None:
        """Connect now (``with`` does this); raises ``ConnectFailed`` or ``PlcTimeout``."""
        self._portal.call(self.client.open)

    def read(self, address: str, count: int = 1) -> list[int] | list[bool]:
        return self._portal.call(self.client.read, address, count)

    def write(self, address: str, values: Points) -> None:
        self._portal.call(self.client.write, address, values)

    @overload
    def read_as(
        self, address: str, vtype: ValueType[T], count: None = None, *, word_order: None = None
    ) -> T: ...

    @overload
    def read_as(
        self, address: str, vtype: ValueType[T], count: int, *, word_order: None = None
    ) -> list[T]: ...

    @overload
    def read_as(
        self,
        address: str,
        vtype: ValueType[T],
        count: int | None = None,
        *,
        word_order: WordOrder,
    ) -> T | list[T]: ...

    @overload
    def read_as(
        self,
        address: str,
        vtype: str,
        count: int | None = None,
        *,
        word_order: WordOrder | None = None,
    ) -> Any: ...

    def read_as(
        self,
        address: str,
        vtype: ValueType[Any] | str,
        count: int | None = None,
        *,
        word_order: WordOrder | None = None,
    ) -> Any:
        """As :meth:`Client.read_as <plcstack.clients.base.Client.read_as>`."""

        async def run() -> Any:
            return await self.client.read_as(address, vtype, count, word_order=word_order)

        return self._portal.call(run)

    def write_as(
        self,
        address: str,
        vtype: ValueType[T] | str,
        value: T | list[T],
        *,
        word_order: WordOrder | None = None,
    ) -> None:
        """As :meth:`Client.write_as <plcstack.clients.base.Client.write_as>`."""

        async def run() -> None:
            await self.client.write_as(address, vtype, value, word_order=word_order)

        self._portal.call(run)

    # -- life cycle -----------------------------------------------------------------------------
    def close(self) -> None:
        """Close the connection and stop the helper thread; later calls raise RuntimeError."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        try:
            self._portal.call(self.client.aclose)
        finally:
            self._stop()

    def __enter__(self) -> Self:
        try:
            self.open()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def connect(url: str, **options: Any) -> SyncClient[Client]:
    """The blocking client for ``url``: the same options as :func:`plcstack.connect` (and the
    same :class:`~plcstack.errors.OptionError` for a bad one, raised before a thread starts).

    Use ``with plcstack.sync.connect(url) as plc:``; without ``with``, the first request
    connects and :meth:`SyncClient.close` must be called.
    """
    client = async_connect(url, **options)
    portal, stop = start_portal()
    return SyncClient(client, portal, stop)


def start_portal() -> tuple[BlockingPortal, Callable[[], None]]:
    """A portal on a new event loop in a daemon thread, and the function that stops both.

    Not anyio's ``start_blocking_portal``: that is a generator context manager, and one left
    open (a script that never called ``close()``) is finalized at interpreter exit by calling into
    its loop thread and joining it, which never returns there: the script hung after its last
    line. Here nothing runs at exit; an unclosed portal's daemon thread simply ends with the
    process.
    """
    ready: concurrent.futures.Future[BlockingPortal] = concurrent.futures.Future()

    async def serve() -> None:
        async with BlockingPortal() as portal:
            ready.set_result(portal)
            await portal.sleep_until_stopped()

    def run() -> None:
        try:
            anyio.run(serve, backend="asyncio")
        except BaseException as exc:  # reported to the caller, or it has its portal already
            if not ready.done():
                ready.set_exception(exc)

    thread = threading.Thread(target=run, name="plcstack-sync", daemon=True)
    thread.start()
    portal = ready.result()

    def stop() -> None:
        with contextlib.suppress(RuntimeError):  # already stopped
            portal.call(portal.stop, True)
        thread.join()

    return portal, stop
