"""One base for everything used with ``async with``: clients, simulators, the poller.

``async with thing:`` runs :meth:`AsyncResource.aopen` (connect, bind, start: whatever makes the
thing usable; nothing by default) and, however the body ends, :meth:`AsyncResource.aclose`. The
same shape as anyio's ``AsyncResource``: ``aclose`` is the one required method, and it must be
safe to call twice.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from types import TracebackType
from typing import Self

__all__ = ["AsyncResource"]


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
