"""One check for every duration a user can give: timeouts, intervals, life-ack periods.

A duration reaches us from a URL query, a keyword argument, a CLI flag or a TOML file. ``inf``
and ``nan`` parse as floats and pass a plain ``> 0`` test (``inf``) or fail it confusingly
(``nan``); ``inf`` then crashed the E71 client deep in its monitoring-timer arithmetic with an
``OverflowError``. Every entry point calls :func:`check_seconds`, so the rule and its wording
exist once; the keyword-option schema can call it per option.
"""

from __future__ import annotations

import math

from plcstack.errors import AddressError

__all__ = ["check_seconds"]


def check_seconds(name: str, value: object, *, plc: str | None = None) -> float:
    """``value`` as a float if it is a finite number of seconds greater than 0, else an
    :class:`~plcstack.errors.AddressError` naming the option (``bool`` is not a number here)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise AddressError(f"option {name}={value!r} is not a number of seconds", plc=plc)
    try:
        seconds = float(value)
    except OverflowError:  # an int too large for a float
        seconds = math.inf
    if not math.isfinite(seconds) or seconds <= 0:
        raise AddressError(
            f"option {name}={value!r} must be a finite number of seconds greater than 0", plc=plc
        )
    return seconds
