"""Jittered exponential backoff for reconnects.

Hundreds of PLCs behind one switch that reboots must not all reconnect in the same millisecond,
hence the jitter; a PLC that stays dead must not be hammered, hence the growth and the cap.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

__all__ = ["Backoff"]


@dataclass
class Backoff:
    """Delay before attempt n: ``min(maximum, initial * factor**n)``, +/- a ``jitter`` share."""

    initial: float = 0.2
    maximum: float = 30.0
    factor: float = 2.0
    jitter: float = 0.25
    _attempt: int = field(default=0, init=False, repr=False)
    _rng: random.Random = field(default_factory=random.Random, repr=False)

    def __post_init__(self) -> None:
        if self.initial < 0 or self.maximum < self.initial or self.factor < 1:
            raise ValueError("backoff needs 0 <= initial <= maximum and factor >= 1")
        if not 0 <= self.jitter <= 1:
            raise ValueError("backoff jitter is a share between 0 and 1")

    @property
    def failures(self) -> int:
        return self._attempt

    def next_delay(self) -> float:
        """Record one more failure and return how long to wait before the next attempt."""
        base = min(self.maximum, self.initial * self.factor**self._attempt)
        self._attempt += 1
        spread = base * self.jitter
        return max(0.0, min(self.maximum, base + self._rng.uniform(-spread, spread)))

    def reset(self) -> None:
        """A connection succeeded: the next failure starts from ``initial`` again."""
        self._attempt = 0
