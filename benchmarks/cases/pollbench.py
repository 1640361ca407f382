"""Fan-out through ``plcstack.poll``: the adapter between the benchmark and the poller's API.

Kept in one module so that a change of the poller's API touches one place.
"""

from __future__ import annotations

import importlib
from typing import Any

from benchmarks.cases import ProtocolCase, Unavailable

__all__ = ["run"]


async def run(
    case: ProtocolCase,
    sims: list[Any],
    base_rss: int | None,
    *,
    repeats: int,
    duration: float,
    warmup: float,
) -> dict[str, Any]:
    try:
        importlib.import_module("plcstack.poll.engine")
    except ModuleNotFoundError:
        raise Unavailable("plcstack.poll not merged yet") from None
    raise Unavailable("poll adapter pending")
