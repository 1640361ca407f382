"""Jittered exponential backoff for reconnects.

Hundreds of PLCs behind one switch that reboots must not all reconnect in the same millisecond,
hence the jitter; a PLC that stays dead must not be hammered, hence the growth and the cap.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

__all__ = ["Backoff"]


@dataclass
class Backoff:
    """Delay before attempt n: ``min(maximum, initial * factor**n)``, +/- a ``jitter`` share.

    The delay stays a finite float however long a PLC stays dead: ``factor**n`` overflows a float
    after 1024 failures (about 8.5 h at the 30 s cap), and every request then raised a bare
    ``OverflowError``; now an overflow simply means "at the cap".
    """

    initial: float = 0.2
    maximum: float = 30.0
    factor: float = 2.0
    jitter: float = 0.25
    _attempt: int = field(default=0, init=False, repr=False)
    _rng: random.Random = field(default_factory=random.Random, repr=False)

    def __post_init__(self) -> None:
        values = (self.initial, self.maximum, self.factor, self.jitter)
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise ValueError("backoff parameters must be finite numbers")
        if self.initial < 0 or self.maximum < self.initial or self.factor < 1:
            raise ValueError("backoff needs 0 <= initial <= maximum and factor >= 1")
        if not 0 <= self.jitter <= 1:
            raise ValueError("backoff jitter is a share between 0 and 1")

    @property
    def failures(self) -> int:
        return self._attempt

    def next_delay(self) -> float:
        """Record one more failure and return how long to wait before the next attempt."""
        base = self._grown()
        self._attempt += 1
        spread = base * self.jitter
        return max(0.0, min(self.maximum, base + self._rng.uniform(-spread, spread)))

    def _grown(self) -> float:
        """``min(maximum, initial * factor**failures)``, never raising: the power overflows a
        float (``OverflowError``) long before ``failures`` stops growing."""
        if self.initial == 0:
            return 0.0
        try:
            grown = self.initial * self.factor**self._attempt
        except OverflowError:
            return self.maximum
        return min(self.maximum, grown)  # a product beyond the float range is inf: capped here

    def reset(self) -> None:
        """A connection proved good: the next failure starts from ``initial`` again."""
        self._attempt = 0
