"""Logger names, the command line's log set-up, and the frame trace.

Loggers follow the package layout, so one name selects a layer or one protocol:
``plcstack.transports.tcp``, ``plcstack.clients.e71``, ``plcstack.sim.fetchwrite``,
``plcstack.poll.engine``, ``plcstack.cli``. The frame trace has its own branch,
``plcstack.frames.PROTOCOL`` (``e71``, ``s5lan``, ``as511``, ``fetchwrite``, ``e71_fixed``): at
DEBUG it logs every chunk a client sends and receives, as hex, with the PLC's name::

    DEBUG plcstack.frames.e71: e71+tcp://127.0.0.1:5000 -> 01 ff 0a 00 64 00 00 00 20 44 02 00
    DEBUG plcstack.frames.e71: e71+tcp://127.0.0.1:5000 <- 81 00 00 00 00 00

Zero cost when off: whether to trace is decided once, when a client is created
(``isEnabledFor``, which the logging module caches), and only then are the transport's
``write``/``read`` wrapped on that one instance. A client created before DEBUG was switched on
is not traced.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Coroutine
from typing import Any

__all__ = ["LEVELS", "configure", "frame_logger", "install_trace"]

#: the values ``--log-level`` accepts
LEVELS = ("debug", "info", "warning", "error")

#: longest frame shown in full; longer ones are cut with the total length said
TRACE_MAX_BYTES = 512


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is at the time of the record, so that ``main()`` called
    in-process (tests capturing stderr) never writes to a stream replaced since."""

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


def configure(level: str) -> Callable[[], None]:
    """Log records of ``plcstack.*`` at ``level`` and above to stderr, one line each.

    Returns the undo (level and handler as before), for ``main()`` called in-process."""
    root = logging.getLogger("plcstack")
    before = root.level
    root.setLevel(level.upper())
    handler = _StderrHandler()
    handler.setFormatter(
        logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    )
    root.addHandler(handler)

    def undo() -> None:
        root.removeHandler(handler)
        root.setLevel(before)

    return undo


def frame_logger(protocol: str) -> logging.Logger:
    return logging.getLogger(f"plcstack.frames.{protocol}")


def hex_frame(data: bytes) -> str:
    """``data`` as spaced hex, cut after :data:`TRACE_MAX_BYTES` bytes."""
    if len(data) <= TRACE_MAX_BYTES:
        return data.hex(" ")
    return f"{data[:TRACE_MAX_BYTES].hex(' ')} ... ({len(data)} bytes)"


def install_trace(transport: Any, name: str, protocol: str) -> bool:
    """Wrap ``transport.write``/``transport.read`` on this instance to log each frame, if the
    protocol's frame logger is enabled for DEBUG. Returns whether it did.

    The transport keeps its class (the clients check ``isinstance`` on it), so only the two
    bound methods are replaced, as instance attributes.
    """
    log = frame_logger(protocol)
    if not log.isEnabledFor(logging.DEBUG):
        return False
    write: Callable[[bytes], None] = transport.write
    read: Callable[..., Coroutine[Any, Any, bytes]] = transport.read

    def traced_write(data: bytes) -> None:
        log.debug("%s -> %s", name, hex_frame(data))
        write(data)

    async def traced_read(deadline: float | None = None) -> bytes:
        data = await read(deadline)
        log.debug("%s <- %s", name, hex_frame(data))
        return data

    send_delivering = getattr(transport, "send_delivering", None)

    class TracedReceiver:
        """Logs each delivered chunk, then hands it to the exchange's receiver."""

        def __init__(self, receiver: Any) -> None:
            self.receiver = receiver

        def chunk_received(self, data: bytes) -> None:
            log.debug("%s <- %s", name, hex_frame(data))
            self.receiver.chunk_received(data)

        def receive_failed(self, exc: Exception) -> None:
            self.receiver.receive_failed(exc)

    def traced_send_delivering(data: bytes, receiver: Any, timeout: float) -> None:
        assert send_delivering is not None
        send_delivering(data, TracedReceiver(receiver), timeout)

    transport.write = traced_write
    transport.read = traced_read
    if send_delivering is not None:
        transport.send_delivering = traced_send_delivering
    return True
