"""What a face may ask of the running configuration: show it, read it again, replace it.

The web console's ``/api/config`` endpoints (and any other face that changes the configuration)
hold a :class:`ConfigControl`; the runtime implements it, so a face never imports the runtime
and a reload asked by SIGHUP, by ``POST /api/config/reload`` or by ``POST /api/config`` takes
the same path: load, check, compute the difference, apply it, log one INFO line and write one
audit record. A file that does not load changes nothing and comes back as the same
``FILE:LINE`` errors as at start.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

__all__ = ["ApplyOutcome", "ConfigControl"]


@dataclass(frozen=True, slots=True)
class ApplyOutcome:
    """The result of one reload or replacement: ``ok`` and the one-line ``summary`` of what
    was applied (``PLCs added: a; removed: b; changed: c`` or ``nothing changed``), or the
    ``errors`` (``FILE:LINE: message``, one a line) of a file that did not load, in which case
    nothing changed."""

    ok: bool
    summary: str = ""
    errors: tuple[str, ...] = ()


class ConfigControl(Protocol):
    """The running configuration, as the runtime lets a face see and change it."""

    @property
    def path(self) -> Path:
        """The configuration file of the run."""
        ...

    def text(self) -> str:
        """The text of the configuration the run applies now (secrets not yet redacted: the
        face that shows it redacts them)."""
        ...

    async def reload(self, *, who: str) -> ApplyOutcome:
        """Read the file again and apply the difference; ``who`` names the asker for the log
        and the audit (``SIGHUP``, ``web 10.0.0.7 (token)``)."""
        ...

    async def replace(self, text: str, *, who: str) -> ApplyOutcome:
        """Check ``text`` as a whole file; if it loads, write it atomically in place of the
        file (the previous one kept as ``FILE.bak``) and apply the difference."""
        ...
