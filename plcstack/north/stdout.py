"""The sample lines of ``plcstack poll`` on stdout (JSON lines, Influx line protocol): a face
of the runtime like the others, so the lines go through the same report-by-exception and the
same supervision (a sample a format cannot print costs that sample, counted under ``stdout``).

A reader of stdout that goes away (``plcstack poll ... | head``) raises ``BrokenPipeError``
out of :meth:`StdoutLines.submit`; the supervisor lets it through, and the run ends cleanly.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from typing import TextIO

from plcstack.north.face import FaceBase, PlcUpdate
from plcstack.poll.config import PlcConfig
from plcstack.poll.samples import Scan

__all__ = ["StdoutLines"]


class StdoutLines(FaceBase):
    """Writes ``text(scans)`` of every batch to ``out`` and flushes it (a batch is handed on
    before the next scan is waited for). ``remake(plcs)``: the text of the PLCs of a reloaded
    file (a float32 tag added is printed at float32 precision); None: ``text`` serves any."""

    name = "stdout"

    def __init__(
        self,
        text: Callable[[Sequence[Scan]], str],
        out: TextIO,
        *,
        remake: Callable[[Sequence[PlcConfig]], Callable[[Sequence[Scan]], str]] | None = None,
    ) -> None:
        self.text = text
        self.out = out
        self.remake = remake

    async def update_plcs(self, update: PlcUpdate) -> None:
        if self.remake is not None:
            self.text = self.remake(update.view.config.plcs)

    def submit(self, scans: Sequence[Scan]) -> None:
        self.out.write(self.text(scans))
        with contextlib.suppress(ValueError):  # a closed stream: nothing more to hand on
            self.out.flush()
