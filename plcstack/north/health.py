"""Health that tells the truth: what each face, sink and state file of a run reports.

Every part of the north side (a face such as the MQTT sink or the OPC UA server, the write
audit, the store-and-forward queue, a supervised task) says how it is with one frozen
:class:`Health`: healthy, or the problem in words, since when, and the figures an operator
needs to judge it (messages waiting). ``/healthz`` (metrics and web console alike) answers 200
only while every part of the run is healthy and 503 otherwise, with one line per part that is
not; ``/livez`` answers 200 while the process runs.

A part keeps its state in a :class:`Condition`: :meth:`Condition.fail` and
:meth:`Condition.clear` return whether the state changed, so its owner logs each change once
(not once per failed attempt), and the time the problem began is kept across repeats of it.
"""

from __future__ import annotations

import datetime
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

__all__ = ["Condition", "Health", "healthz_body", "several", "unhealthy"]


def _iso(when: float) -> str:
    stamp = datetime.datetime.fromtimestamp(when, datetime.UTC)
    return stamp.strftime("%Y-%m-%dT%H:%M:%SZ")


def _since(when: float, now: float | None) -> str:
    """`` since 2026-11-25T21:50:01Z (12 s ago)``."""
    age = max(0, round((time.time() if now is None else now) - when))
    return f" since {_iso(when)} ({age} s ago)"


@dataclass(frozen=True, slots=True)
class Health:
    """How one part of the run is: ``problem`` None while healthy, else why not in words,
    ``since`` (Unix time) when that began, and ``figures`` such as ``("messages waiting",
    269)``."""

    name: str
    problem: str | None = None
    since: float | None = None
    figures: tuple[tuple[str, int], ...] = ()

    @property
    def ok(self) -> bool:
        return self.problem is None

    def line(self, now: float | None = None) -> str:
        """One line for ``/healthz`` and logs: ``mqtt: MQTT broker mqtt://b:1883 unreachable
        since 2026-11-25T21:50:01Z (12 s ago), 269 messages waiting``; ``NAME: ok`` if
        healthy."""
        if self.problem is None:
            text = f"{self.name}: ok"
        else:
            text = f"{self.name}: {self.problem}"
            if self.since is not None:
                text += _since(self.since, now)
        if self.figures:
            text += ", " + ", ".join(f"{value} {what}" for what, value in self.figures)
        return text


def several(
    name: str,
    problems: Sequence[tuple[str, float | None]],
    figures: tuple[tuple[str, int], ...] = (),
    now: float | None = None,
) -> Health:
    """The health of a part that can have more than one problem at once (its broker away and
    the disk under its queue full): each problem said with its own since when, in the order
    given; healthy without any."""
    if not problems:
        return Health(name, figures=figures)
    *first, (last, since) = problems
    text = "".join(f"{p}{_since(s, now) if s is not None else ''}; " for p, s in first)
    return Health(name, text + last, since, figures)


def unhealthy(parts: Iterable[Health]) -> list[Health]:
    """The parts that are not healthy, in the order given."""
    return [h for h in parts if h.problem is not None]


def healthz_body(parts: Iterable[Health], now: float | None = None) -> tuple[bool, str]:
    """``(healthy, text)`` of ``/healthz``: ``ok`` and one line per part while all are
    healthy; else one line per part that is not (the first lines: what an alert shows)."""
    parts = list(parts)
    bad = unhealthy(parts)
    if not bad:
        return True, "ok\n" + "".join(h.line(now) + "\n" for h in parts)
    return False, "".join(h.line(now) + "\n" for h in bad)


class Condition:
    """The current problem of one part, and since when; see the module docstring."""

    __slots__ = ("name", "problem", "since")

    def __init__(self, name: str) -> None:
        self.name = name
        self.problem: str | None = None
        self.since: float | None = None

    def fail(self, problem: str, now: float | None = None) -> bool:
        """Note ``problem``; True if the part was healthy or had another problem before (the
        owner logs it then). ``since`` keeps the time the part stopped being healthy."""
        changed = problem != self.problem
        if self.problem is None:
            self.since = time.time() if now is None else now
        self.problem = problem
        return changed

    def clear(self) -> bool:
        """Healthy again; True if it was not (the owner logs the recovery then)."""
        if self.problem is None:
            return False
        self.problem = None
        self.since = None
        return True

    def health(self, figures: tuple[tuple[str, int], ...] = ()) -> Health:
        return Health(self.name, self.problem, self.since, figures)
