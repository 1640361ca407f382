"""What every state file plcstack keeps does with a damaged one: moves it aside and starts anew.

A state file (the store-and-forward queue, the Sparkplug ``bdSeq``) that cannot be read as what
it should be (random bytes, a truncated database, a page of garbage, another program's schema)
must not keep a gateway dark until someone deletes it by hand, and must not be deleted either:
it may hold the only copy of data someone wants to recover. So it is renamed beside itself,
``mqtt.sqlite`` -> ``mqtt.corrupt-20261125T215001Z.sqlite``, with its companion files (SQLite's
``-wal`` and ``-shm``) under the same new name, one WARNING names both paths and why, and the
caller starts with an empty state.
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["aside_name", "fsync_directory", "move_aside"]


def aside_name(path: Path, now: float) -> Path:
    """Where ``path`` goes: beside itself, ``corrupt`` and the UTC time in its name, the suffix
    kept (a file manager still knows it); ``-2``, ``-3`` ... if that name is taken."""
    stamp = datetime.datetime.fromtimestamp(now, datetime.UTC).strftime("%Y%m%dT%H%M%SZ")
    base = f"{path.stem}.corrupt-{stamp}"
    candidate = path.with_name(f"{base}{path.suffix}")
    n = 2
    while candidate.exists():
        candidate = path.with_name(f"{base}-{n}{path.suffix}")
        n += 1
    return candidate


def move_aside(
    path: Path,
    why: str,
    *,
    what: str,
    then: str,
    logger: logging.Logger,
    companions: Sequence[str] = (),
    now: float | None = None,
) -> Path | None:
    """Rename the damaged ``path`` (and ``path + suffix`` for each of ``companions`` that
    exists) aside; one WARNING: ``{what} {path} is damaged ({why}): moved aside to {new};
    {then}``. The new path, or None (an ERROR says why) when the rename itself failed."""
    target = aside_name(path, time.time() if now is None else now)
    try:
        os.replace(path, target)
    except FileNotFoundError:
        target_text = "nothing to move (it is gone)"
    except OSError as exc:
        logger.error(
            "%s %s is damaged (%s) and cannot be moved aside (%s); %s",
            what,
            path,
            why,
            exc.strerror or exc,
            then,
        )
        return None
    else:
        target_text = f"moved aside to {target}"
    for suffix in companions:
        companion = Path(f"{path}{suffix}")
        if companion.exists():
            try:
                os.replace(companion, Path(f"{target}{suffix}"))
            except OSError as exc:  # a stale companion must not be read with a new file
                logger.error("%s: cannot move %s aside (%s)", what, companion, exc.strerror or exc)
                with contextlib.suppress(OSError):
                    companion.unlink()
    logger.warning("%s %s is damaged (%s): %s; %s", what, path, why, target_text, then)
    return target


def fsync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable (POSIX: the directory's entry is flushed too);
    not possible everywhere, never fatal."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
