"""Loopback port numbers for tests that must name a port before anything binds it.

A server in another process (mosquitto, nats-server, influxd, a ``plcstack`` subprocess), a
config file, or a documented command with its port moved all need a number first. The kernel's
port 0 gives one that is free at that moment and at once the kernel's to hand out again: to
another test's outgoing connection as its local port, or to another port-0 bind. The server then
fails to bind it, or the test talks to a stranger that got there first (seen as a simulator's
port resetting connections, and as a walkthrough waiting for workers that never reached their
broker). And a client that connects to a closed port in the ephemeral range can, now and then,
be given that very port as its own and connect to itself.

So ports come from below the kernel's ephemeral range (``ip_local_port_range``), which it never
hands out by itself; and every port handed out is reserved with a lock file for as long as this
process keeps it (the last :data:`KEEP` ports), so parallel test processes (xdist workers,
another suite on the same machine) never get the same one. A lock dies with its process, so a
crashed run leaves nothing behind to clean up.
"""

from __future__ import annotations

import collections
import fcntl
import os
import socket
import tempfile
from pathlib import Path

__all__ = ["KEEP", "free_port", "free_ports_in_a_row", "port_range"]

#: how many ports one process keeps reserved (the oldest is released for each new one; a test
#: uses its ports long before this many more have been handed out)
KEEP = 512
#: how many ports below the ephemeral range are used
SPAN = 12000
_LOCKS = Path(tempfile.gettempdir()) / "plcstack-test-ports"
_held: collections.deque[tuple[int, int]] = collections.deque()  # (port, lock fd)
_cursor: list[int] = []


def port_range() -> range:
    """The ports this module hands out: the :data:`SPAN` just below the ephemeral range, or
    above it when the range starts too low to leave room."""
    try:
        low, high = map(int, Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    except (OSError, ValueError):
        low, high = 32768, 60999  # Linux's default
    if low - 1024 >= SPAN // 3:
        return range(max(1024, low - SPAN), low)
    if 65535 - high >= SPAN // 3:
        return range(high + 1, min(65536, high + 1 + SPAN))
    raise RuntimeError(
        f"the ephemeral port range {low}-{high} leaves no room for fixed test ports below or "
        "above it; narrow it (sysctl net.ipv4.ip_local_port_range)"
    )


def _bindable(host: str, port: int) -> bool:
    """Nothing has this port now, for TCP or UDP."""
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind((host, port))
            except OSError:
                return False
    return True


def _reserve(port: int) -> int | None:
    """The lock file's descriptor if this process now holds ``port``, else None."""
    _LOCKS.mkdir(exist_ok=True)
    fd = os.open(_LOCKS / str(port), os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def free_port(host: str = "127.0.0.1") -> int:
    """A port nothing listens on, that no other test process is handed while this one keeps
    it, and that the kernel does not give to outgoing connections."""
    return free_ports_in_a_row(1, host)


def free_ports_in_a_row(count: int, host: str = "127.0.0.1") -> int:
    """The first of ``count`` consecutive ports, each as :func:`free_port` gives one (for a
    command that takes a base port and uses the ones after it)."""
    ports = port_range()
    if not _cursor:  # processes start at different places, so they seldom probe the same port
        _cursor.append(os.getpid() * 7919 % len(ports))
    for _ in range(len(ports)):
        first = _cursor[0]
        _cursor[0] = (first + count) % len(ports)
        if first + count > len(ports):
            continue  # would run past the end of the range
        taken = _take(ports[first : first + count], host)
        if taken is not None:
            _held.extend(taken)
            while len(_held) > KEEP:
                os.close(_held.popleft()[1])
            return ports[first]
    raise RuntimeError(f"no {count} free ports in {ports.start}-{ports.stop - 1} on {host}")


def _take(ports: range, host: str) -> list[tuple[int, int]] | None:
    """Each of ``ports`` reserved and bindable now, or None (with nothing kept)."""
    taken: list[tuple[int, int]] = []
    for port in ports:
        fd = None if any(port == held for held, _ in _held) else _reserve(port)
        if fd is not None and not _bindable(host, port):
            os.close(fd)
            fd = None
        if fd is None:  # this process or another one has it, or something listens there
            for _, taken_fd in taken:
                os.close(taken_fd)
            return None
        taken.append((port, fd))
    return taken
