"""Logger names, the command line's log set-up (terminal, journald, JSON), and the frame trace.

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

Where the lines go (:func:`configure`), one line per record on stderr:

- on a terminal: ``12:00:01 WARNING plcstack.north: PLC press1 is offline: ...``;
- under systemd, when ``JOURNAL_STREAM`` names this process's stderr (device and inode, as
  systemd.exec(5) says to check): ``<4>plcstack.north: PLC press1 is offline: ...``, the
  syslog priority first (journald files the line under it and strips it) and no time of its
  own (journald stamps every line); each line of a traceback gets the prefix too;
- ``--log-format json``: one JSON object per line, ``{"time", "level", "logger", "message"}``
  and, where the record carries them (``log.warning(..., extra={"plc": name})``), ``plc``,
  ``tag``, ``face``; an exception as ``exception``. Under journald with the priority first.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import sys
from collections.abc import Callable, Coroutine, Mapping
from typing import Any

__all__ = [
    "FORMATS",
    "LEVELS",
    "configure",
    "frame_logger",
    "install_trace",
    "journal_priority",
    "on_journal",
]

#: the values ``--log-level`` accepts
LEVELS = ("debug", "info", "warning", "error")
#: the values ``--log-format`` accepts
FORMATS = ("text", "json")
#: the record attributes a JSON line carries when the record has them (``extra=``)
CONTEXT = ("plc", "tag", "face")

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


def on_journal(environ: Mapping[str, str] | None = None, fd: int = 2) -> bool:
    """Whether ``fd`` (stderr) is the stream systemd connected to journald: ``JOURNAL_STREAM``
    is ``DEVICE:INODE`` of it. A child whose stderr was redirected elsewhere inherits the
    variable but not the stream, so the comparison, not the variable alone, decides."""
    env = os.environ if environ is None else environ
    device, _, inode = env.get("JOURNAL_STREAM", "").partition(":")
    try:
        st = os.fstat(fd)
        return (st.st_dev, st.st_ino) == (int(device), int(inode))
    except (OSError, ValueError):
        return False


def journal_priority(levelno: int) -> int:
    """The syslog priority of a logging level: 2 critical, 3 error, 4 warning, 6 info,
    7 debug (and 5, notice, for a level between warning and info)."""
    if levelno >= logging.CRITICAL:
        return 2
    if levelno >= logging.ERROR:
        return 3
    if levelno >= logging.WARNING:
        return 4
    if levelno > logging.INFO:
        return 5
    if levelno >= logging.INFO:
        return 6
    return 7


class _JournalFormatter(logging.Formatter):
    """Prefixes every line of what ``inner`` made with the record's syslog priority."""

    def __init__(self, inner: logging.Formatter) -> None:
        super().__init__()
        self.inner = inner

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{journal_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in self.inner.format(record).split("\n"))


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (a message's newlines are escaped in it)."""

    def format(self, record: logging.LogRecord) -> str:
        created = datetime.datetime.fromtimestamp(record.created, datetime.UTC)
        line: dict[str, object] = {
            "time": created.strftime("%Y-%m-%dT%H:%M:%S.") + f"{created.microsecond // 1000:03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key in CONTEXT:
            value = record.__dict__.get(key)
            if value is not None:
                line[key] = value if isinstance(value, str | int | float | bool) else str(value)
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        return json.dumps(line, ensure_ascii=False, default=str)


def formatter(log_format: str = "text", *, journal: bool = False) -> logging.Formatter:
    """The formatter of :func:`configure`'s handler (see the module's docstring)."""
    if log_format not in FORMATS:
        raise ValueError(f"log format must be one of {', '.join(FORMATS)}, not {log_format!r}")
    inner: logging.Formatter
    if log_format == "json":
        inner = JsonFormatter()
    elif journal:
        inner = logging.Formatter("%(name)s: %(message)s")
    else:
        return logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    return _JournalFormatter(inner) if journal else inner


def configure(level: str, log_format: str = "text") -> Callable[[], None]:
    """Log records of ``plcstack.*`` at ``level`` and above to stderr, one line each, in
    ``log_format`` (``text`` or ``json``), for journald when stderr is its stream.

    Returns the undo (level and handler as before), for ``main()`` called in-process."""
    root = logging.getLogger("plcstack")
    before = root.level
    root.setLevel(level.upper())
    handler = _StderrHandler()
    handler.setFormatter(formatter(log_format, journal=on_journal()))
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
