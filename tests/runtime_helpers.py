"""Faces fed by the runtime in tests: the one consumer of the poller's scans, as ``plcstack
poll`` feeds every face (no test feeds a face on a path of its own)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

from plcstack.north.config import NorthConfig
from plcstack.north.face import Face, ScanSource
from plcstack.north.pipeline import North


@contextlib.asynccontextmanager
async def fed(poller: ScanSource, *faces: Face) -> AsyncIterator[North]:
    """``faces`` (started by the caller, as the poller is) fed with the poller's scans by the
    runtime's consumer until the block ends."""
    north = North(poller, NorthConfig(), faces=faces)
    feed = asyncio.create_task(north.run(), name="the runtime's consumer")
    try:
        yield north
    finally:
        feed.cancel()
        await asyncio.gather(feed, return_exceptions=True)
        if not feed.cancelled() and feed.exception() is not None:
            raise AssertionError("the consumer failed") from feed.exception()
