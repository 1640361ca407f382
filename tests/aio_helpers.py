"""Helpers for the tests' own asyncio servers."""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Awaitable, Callable

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
