"""What is benchmarked per protocol: simulator, client URL, the 64-word jobs, floor bytes, codec.

Each protocol variant (``e71+tcp``, ``fetchwrite+mk``, ...) is one :class:`ProtocolCase`. The case
modules build the same two jobs everywhere: **read 64 words** and **write 64 words** at a data area
the simulator was filled with known values, so the warm-up can check that floor and stack really
read what the simulator holds before anything is timed.

A protocol whose client or simulator is not on this branch yet raises :class:`Unavailable` from
:meth:`ProtocolCase.check`; the suite then reports the case as skipped with that note.
"""

from __future__ import annotations

import importlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

from plcstack.bench.frames import FloorJob, ScriptJob

__all__ = ["WORDS", "CodecOps", "ProtocolCase", "Unavailable", "sample_words"]

#: points per job: "a typical read (64 words)"
WORDS = 64


def sample_words(count: int = WORDS, seed: int = 0x1010) -> list[int]:
    """Deterministic words that include bytes 10h (AS511 DLE stuffing) and high bits."""
    return [(seed + i * 0x0107) & 0xFFFF for i in range(count)]


class Unavailable(Exception):
    """This case cannot run here (protocol not merged yet, optional peer not installed)."""


@dataclass
class CodecOps:
    """Zero-argument callables for the codec micro-benchmark (each does one full operation)."""

    stack_read: Callable[[], object]
    stack_write: Callable[[], object]
    floor_read: Callable[[], object]
    floor_write: Callable[[], object]


@dataclass
class ProtocolCase:
    """One protocol variant as the one-connection and fan-out cases drive it."""

    key: str
    #: modules that must import for the case to run (simulator, client, codec)
    modules: tuple[str, ...]
    sim_module: str
    #: build the simulator's memory already holding ``sample_words()`` at the read address
    make_memory: Callable[[ModuleType], Any]
    #: extra keyword arguments for ``sim.start``
    sim_kwargs: dict[str, Any] = field(default_factory=dict)
    #: turn ``sim.url`` into the URL the stack client uses (e.g. add ``?mk=1``)
    client_url: Callable[[str], str] = lambda url: url
    read_address: str = ""
    write_address: str = ""
    floor_read: Callable[[], FloorJob | ScriptJob] | None = None
    floor_write: Callable[[], FloorJob | ScriptJob] | None = None
    udp: bool = False
    #: codec micro-benchmark builder (``None``: this variant shares another variant's codec row)
    codec: Callable[[], CodecOps] | None = None
    #: optional coroutine run on the opened stack client before timing (e.g. warm a cache)
    prepare_client: Callable[[Any], Awaitable[None]] | None = None

    def check(self) -> None:
        for name in self.modules:
            try:
                importlib.import_module(name)
            except ModuleNotFoundError as exc:
                if exc.name is not None and name.startswith(exc.name):
                    raise Unavailable(f"not merged yet ({name} missing)") from None
                raise

    def sim(self) -> ModuleType:
        return importlib.import_module(self.sim_module)
