"""Serial transport on pyserial-asyncio (AS511 at 9600 8E1 by default).

Pseudo-terminal parity fallback
-------------------------------
Tests and the simulator connect over a pseudo-terminal pair instead of a cable. A pty has no line
discipline for parity. This kernel drops ``PARENB`` on a pty silently when other flags change in
the same ``tcsetattr`` (a first open "succeeds" without parity), and rejects it with
``termios.error: EINVAL`` when parity is the only change (every re-open of the same pty).
Parity means nothing on a pty (bytes are passed through, never framed), so when the device is a
pseudo-terminal and setting the requested parity fails, we open it again with ``PARITY_NONE`` and
log one warning. A real serial device that rejects the settings is an error (``ConnectFailed``):
silently dropping parity on a real line would garble every byte the CPU sends.
"""

from __future__ import annotations

import asyncio
import logging
import os
import stat
from collections.abc import Callable
from typing import Any

import serial
import serial_asyncio

from plcstack.errors import ConnectFailed, PlcTimeout
from plcstack.transports.base import ProtocolTransport, QueueProtocolMixin
from plcstack.transports.tap import Endpoints, Tap, combined

__all__ = ["PARITIES", "SerialTransport", "is_pty"]

try:  # POSIX only; on Windows there are no ptys and pyserial reports errors as SerialException
    import termios

    _OPEN_ERRORS: tuple[type[BaseException], ...] = (OSError, ValueError, termios.error)
except ImportError:  # pragma: no cover
    _OPEN_ERRORS = (OSError, ValueError)

log = logging.getLogger(__name__)

#: URL spelling -> pyserial constant
PARITIES = {
    "N": serial.PARITY_NONE,
    "E": serial.PARITY_EVEN,
    "O": serial.PARITY_ODD,
}

#: Linux major device numbers of Unix98 pty slaves (/dev/pts/N): 136..143
_PTY_MAJORS = range(136, 144)


def is_pty(path: str) -> bool:
    """True when ``path`` is the slave end of a pseudo-terminal (``/dev/pts/N`` or a link to it)."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    if not stat.S_ISCHR(st.st_mode):
        return False
    return os.major(st.st_rdev) in _PTY_MAJORS or os.path.realpath(path).startswith("/dev/pts/")


class _SerialProtocol(QueueProtocolMixin, asyncio.Protocol):
    def __init__(self, peer: str) -> None:
        self._init_queue(peer)

    def data_received(self, data: bytes) -> None:
        self._push(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self._fail(exc or EOFError("serial port closed"))


class _TappedSerialProtocol(_SerialProtocol):
    """A recorded line (:mod:`.tap`): every chunk is told to the tap before it is handled."""

    def __init__(self, peer: str, tap: Tap) -> None:
        super().__init__(peer)
        # here, not in ``connection_made``: pyserial-asyncio makes the protocol once the port
        # is open but calls ``connection_made`` a loop pass later, after the first send
        self.wire = tap.connection(Endpoints("serial", ("", 0), ("", 0), "local", peer))

    def data_received(self, data: bytes) -> None:
        if self.wire is not None:
            self.wire.received(data)
        super().data_received(data)

    def connection_lost(self, exc: Exception | None) -> None:
        wire, self.wire = self.wire, None
        if wire is not None:
            wire.ended(by_peer=exc is not None)
        super().connection_lost(exc)


class SerialTransport(ProtocolTransport):
    """One serial port; ``open()`` again after a close re-opens the device.

    ``parity_fallback`` is set after ``open()`` when a pty refused the requested parity and the
    port was opened without it (see the module docstring).
    """

    def __init__(
        self,
        path: str,
        *,
        baudrate: int = 9600,
        bytesize: int = 8,
        parity: str = "E",
        stopbits: float = 1,
    ) -> None:
        if parity not in PARITIES:
            raise ValueError(f"parity {parity!r} is not one of N, E, O")
        if stopbits not in (1, 1.5, 2):
            raise ValueError(f"stop bits {stopbits} is not 1, 1.5 or 2")
        super().__init__(path)
        self.path = path
        self.baudrate = baudrate
        self.bytesize = bytesize
        self.parity = parity
        self.stopbits = stopbits
        self.parity_fallback = False

    @property
    def byte_time(self) -> float:
        """Line time of one character: start + data + parity + stop bits over the baud rate."""
        bits = 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits
        return bits / self.baudrate

    async def _create(self, parity: str) -> tuple[Any, _SerialProtocol]:
        loop = asyncio.get_running_loop()
        tap = combined(self._tap)
        peer = self.peer
        factory: Callable[[], _SerialProtocol] = (
            (lambda: _SerialProtocol(peer))
            if tap is None
            else (lambda: _TappedSerialProtocol(peer, tap))
        )
        result: tuple[Any, _SerialProtocol] = await serial_asyncio.create_serial_connection(
            loop,
            factory,
            self.path,
            baudrate=self.baudrate,
            bytesize=self.bytesize,
            parity=PARITIES[parity],
            stopbits=self.stopbits,
        )
        return result

    async def _open_once(self, parity: str, timeout: float | None) -> tuple[Any, _SerialProtocol]:
        try:
            async with asyncio.timeout(timeout):
                return await self._create(parity)
        except TimeoutError:
            raise PlcTimeout(f"opening {self.path} timed out after {timeout} s") from None

    async def open(self, timeout: float | None) -> None:
        self.abort()
        self.parity_fallback = False
        try:
            transport, protocol = await self._open_once(self.parity, timeout)
        except _OPEN_ERRORS as exc:  # SerialException is an OSError
            if self.parity == "N" or not is_pty(self.path):
                raise ConnectFailed(f"cannot open serial port {self.path}: {exc}") from None
            # Documented fallback (module docstring): ptys reject PARENB here. INFO, not
            # WARNING: it is expected on every pty (only simulators use them), and a warning
            # reached stderr through logging's last-resort handler, so a one-shot CLI error
            # was no longer one line (tests/test_robustness_cli.py, as511-pty).
            log.log(
                logging.INFO,
                "%s is a pseudo-terminal that rejects parity %s (%s); opened without parity",
                self.path,
                self.parity,
                exc,
            )
            try:
                transport, protocol = await self._open_once("N", timeout)
            except _OPEN_ERRORS as exc2:
                raise ConnectFailed(f"cannot open serial port {self.path}: {exc2}") from None
            self.parity_fallback = True
        self._opened(transport, protocol, transport.write)

    async def aclose(self) -> None:
        transport, protocol = self._transport, self._protocol
        self._transport = None
        self._protocol = None
        if transport is None or protocol is None:
            return
        # pyserial-asyncio writes from a writer callback: the last bytes written (an AS511
        # PG's closing DLE ACK) are still buffered here. Let them go out before the port is
        # let go; a line that takes nothing for a second is cut off.
        await self._close_flushed(transport, protocol)
