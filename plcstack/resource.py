"""One base for everything used with ``async with``: clients, simulators, the poller.

``async with thing:`` runs :meth:`AsyncResource.aopen` (connect, bind, start: whatever makes the
thing usable; nothing by default) and, however the body ends, :meth:`AsyncResource.aclose`. The
same shape as anyio's ``AsyncResource``: ``aclose`` is the one required method, and it must be
safe to call twice.
"""

from __future__ import annotations

import asyncio
from abc import ABC, abstractmethod
from collections.abc import Iterable
from types import TracebackType
from typing import Any, Self

__all__ = ["AsyncResource", "cancel_until_done"]

#: seconds between the cancels of a task that is still running
_RECANCEL = 0.5


async def cancel_until_done(tasks: Iterable[asyncio.Task[Any]]) -> None:
    """Cancel ``tasks`` and return once each has really ended (their outcome is the caller's
    to read).

    One cancel is not always enough on Python 3.11: an ``asyncio.wait_for`` whose result
    arrives together with the cancel returns the result and drops the cancel (ours, or one
    inside a library: nats-py waits for every request that way), and the task carries on. A
    resource that stopped its tasks with one cancel and then waited for them could wait for
    ever; so a task still running is cancelled again every half second.
    """
    pending = {task for task in tasks if not task.done()}
    while pending:
        for task in pending:
            task.cancel()
        _, pending = await asyncio.wait(pending, timeout=_RECANCEL)


class AsyncResource(ABC):
    """Something to close with ``await x.aclose()``; ``async with x`` opens and closes it."""

    __slots__ = ()

    async def aopen(self) -> None:
        """Make the resource usable; ``async with`` calls it before the body. Default: nothing."""

    @abstractmethod
    async def aclose(self) -> None:
        """Release everything the resource holds; a second call does nothing."""

    async def __aenter__(self) -> Self:
        await self.aopen()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()
