"""Helpers for the tests' own asyncio servers, and waiting for a condition."""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Awaitable, Callable
from typing import Any

__all__ = [
    "Handler",
    "blocked_until",
    "ended_by_server",
    "ends_quietly",
    "eventually",
    "poll_tasks_left",
]

Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


def ends_quietly(handler: Handler) -> Handler:
    """Wrap an ``asyncio.start_server`` handler so that it ends normally when cancelled.

    On Python 3.11 the stream protocol's done-callback calls ``task.exception()`` on the handler
    task, which raises for a cancelled task: every test server whose connections are cancelled
    at teardown (``aclose``, or the loop closing) then logs "Exception in callback". A
    cancelled connection of a test server is the normal end of a test, not an error.
    """

    @functools.wraps(handler)
    async def run(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await handler(reader, writer)
        except asyncio.CancelledError:
            writer.transport.abort()

    return run


async def eventually(condition: Callable[[], object], what: str, timeout: float = 10.0) -> None:
    """Wait until ``condition()`` is true, polling every 10 ms; an ``AssertionError`` naming
    ``what`` after ``timeout`` seconds.

    For the "by now it has happened" of a test (the sink noticed the broker is gone, the client
    tried again): a fixed sleep guesses how long that takes and fails on a loaded machine, while
    a condition with a generous bound costs only the time it really takes.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not condition():
        if loop.time() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        await asyncio.sleep(0.01)


def blocked_until(condition: Callable[[], object], what: str, timeout: float = 10.0) -> None:
    """:func:`eventually` that blocks the event loop meanwhile: for "the bytes wait in the
    kernel, the loop has not read them", which only a loop that does not run can promise.

    The peer that sends them must not need this loop (a thread, another process, the kernel).
    """
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        time.sleep(0.005)


def poll_tasks_left() -> list[asyncio.Task[Any]]:
    """Tasks of the poller (its PLC tasks and task-path scans) still alive, besides the
    caller's: after ``Poller.aclose`` there must be none."""
    return [
        t
        for t in asyncio.all_tasks()
        if t is not asyncio.current_task() and "poll" in repr(t.get_coro())
    ]


async def ended_by_server(reader: asyncio.StreamReader, bound: float = 5.0) -> bool:
    """Whether the server closed or reset the connection within ``bound`` seconds (what it
    sent meanwhile is read and dropped)."""
    try:
        async with asyncio.timeout(bound):
            while await reader.read(65536):
                pass
        return True
    except ConnectionError:
        return True
    except TimeoutError:
        return False
