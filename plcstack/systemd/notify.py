"""The service manager's notify protocol (sd_notify(3)), without libsystemd.

systemd starts a ``Type=notify`` service with ``NOTIFY_SOCKET`` naming a Unix datagram socket:
a file path (``/run/systemd/notify``) or, starting with ``@``, a name in Linux's abstract
namespace. Each message is one datagram of newline-separated ``NAME=value`` assignments
(``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``RELOADING=1`` with ``MONOTONIC_USEC=``,
``STOPPING=1``); the kernel adds the sender's credentials, by which systemd knows the message
is the service's. ``WATCHDOG_USEC`` asks for ``WATCHDOG=1`` at least that often (sent at half
of it, as sd_watchdog_enabled(3) advises), unless ``WATCHDOG_PID`` names another process.

Sending never blocks the event loop and never raises: a datagram the socket does not take is
counted and said once per run of failures (WARNING naming the socket and the reason), since a
service that cannot reach its manager still serves its PLCs; systemd then acts as it would on
silence (a start that times out, a watchdog restart), and the log line says why.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Mapping

__all__ = ["Notifier", "monotonic_usec"]

log = logging.getLogger("plcstack.systemd")


def monotonic_usec() -> int:
    """CLOCK_MONOTONIC in microseconds, the clock ``MONOTONIC_USEC=`` is read on."""
    return time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000


class Notifier:
    """Datagrams to the service manager's notify socket; a notifier without one does nothing.

    ``address`` is ``NOTIFY_SOCKET`` as systemd sets it (None or "": not under systemd);
    ``watchdog_usec`` is ``WATCHDOG_USEC`` (None: no watchdog).
    """

    def __init__(self, address: str | None, *, watchdog_usec: int | None = None) -> None:
        self.address = address or None
        #: seconds between two ``WATCHDOG=1`` (half the manager's timeout); None: no watchdog
        self.watchdog_interval: float | None = None
        if watchdog_usec is not None:
            if watchdog_usec <= 0:
                raise ValueError(f"WATCHDOG_USEC must be a positive number, not {watchdog_usec}")
            self.watchdog_interval = watchdog_usec / 2e6
        #: datagrams the socket took, and those it did not
        self.sent = 0
        self.failed = 0
        self._failing = False
        self._target: bytes | None = None
        self._socket: socket.socket | None = None
        if self.address is None:
            return
        if self.address.startswith("@"):
            self._target = b"\0" + os.fsencode(self.address[1:])
        elif self.address.startswith("/"):
            self._target = os.fsencode(self.address)
        else:  # e.g. vsock:CID:PORT (systemd 254): not a Unix socket
            log.warning(
                "NOTIFY_SOCKET=%s is neither a socket path nor an abstract socket (@name):"
                " the service manager will not hear from plcstack",
                self.address,
            )
            return
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self._socket.setblocking(False)

    @classmethod
    def from_environment(
        cls, environ: Mapping[str, str] | None = None, *, pid: int | None = None
    ) -> Notifier:
        """The notifier ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` ask for. A
        watchdog meant for another process (``WATCHDOG_PID``) or a malformed value is no
        watchdog (the malformed one said in a WARNING)."""
        env = os.environ if environ is None else environ
        usec: int | None = None
        text = env.get("WATCHDOG_USEC")
        if text:
            owner = env.get("WATCHDOG_PID")
            mine = str(os.getpid() if pid is None else pid)
            try:
                usec = int(text)
                if usec <= 0:
                    raise ValueError
            except ValueError:
                log.warning("WATCHDOG_USEC=%s is not a positive number: no watchdog pings", text)
                usec = None
            if owner and owner != mine:
                usec = None  # the watchdog of a parent process, not ours
        return cls(env.get("NOTIFY_SOCKET"), watchdog_usec=usec)

    @property
    def enabled(self) -> bool:
        """Whether there is a socket to send to."""
        return self._socket is not None

    def send(self, *assignments: str) -> bool:
        """One datagram of ``NAME=value`` assignments; whether the socket took it (False also
        without a socket)."""
        sock, target = self._socket, self._target
        if sock is None or target is None:
            return False
        text = "\n".join(" ".join(a.splitlines()) for a in assignments)
        try:
            sock.sendto(text.encode(), target)
        except OSError as exc:
            self.failed += 1
            if not self._failing:
                self._failing = True
                log.warning(
                    "cannot notify the service manager at %s (%s): %s: the notifications"
                    " stop until the socket takes them again",
                    self.address,
                    assignments[0] if assignments else "",
                    exc.strerror or exc,
                )
            return False
        self.sent += 1
        if self._failing:
            self._failing = False
            log.warning("the service manager at %s takes notifications again", self.address)
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.send("READY=1", *([f"STATUS={status}"] if status is not None else []))

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text}")

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def reloading(self, status: str | None = None) -> bool:
        """``RELOADING=1`` with the time it began, as ``Type=notify-reload`` requires."""
        extra = [f"STATUS={status}"] if status is not None else []
        return self.send("RELOADING=1", f"MONOTONIC_USEC={monotonic_usec()}", *extra)

    def stopping(self, status: str | None = None) -> bool:
        return self.send("STOPPING=1", *([f"STATUS={status}"] if status is not None else []))

    def close(self) -> None:
        sock, self._socket = self._socket, None
        if sock is not None:
            sock.close()
