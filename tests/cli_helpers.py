"""Running the ``plcstack`` command line from a test without starting a new interpreter.

A subprocess ``python -m plcstack ...`` imports the whole package again: 0.3-0.8 s of CPU per
command, and the CLI tests ran dozens of them one after the other. ``cli_in_process`` runs the
same ``plcstack.cli.main`` (the function ``python -m plcstack`` calls) in a worker thread with its
stdout and stderr captured, and returns what a subprocess gives: exit code, stdout, stderr.
``main`` runs its command with ``asyncio.run`` in that thread, so the test's own event loop (the
simulator) keeps serving meanwhile; ``main`` undoes its logging set-up when it returns.

Not for commands that install signal handlers (``sim``, ``poll``, ``demo``, ``gateway``): only a
main thread may. The entry point itself (``python -m plcstack``, exit statuses, signals) keeps its
subprocess tests in test_cli_basic.py and test_cli_rules.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import threading

from plcstack.cli import main

__all__ = ["cli_in_process"]

#: sys.stdout/sys.stderr are process-wide: one in-process command at a time
_REDIRECT = threading.Lock()


def _stream() -> io.TextIOWrapper:
    # a text stream with a .buffer, like the real ones; not a terminal (isatty() is False)
    return io.TextIOWrapper(io.BytesIO(), encoding="utf-8", newline="", write_through=True)


def _text(stream: io.TextIOWrapper) -> str:
    stream.flush()
    raw = stream.buffer
    assert isinstance(raw, io.BytesIO)
    return raw.getvalue().decode()


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = _stream(), _stream()
    with _REDIRECT, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, _text(out), _text(err)


async def cli_in_process(*args: str, timeout: float = 30) -> tuple[int, str, str]:
    """``plcstack ARGS`` in this process: (exit code, stdout, stderr)."""
    return await asyncio.wait_for(asyncio.to_thread(_run, list(args)), timeout)
