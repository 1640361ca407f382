"""The test ports: outside the kernel's range, skipped while taken, never shared between
processes."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

from tests import ports
from tests.ports import free_port, free_ports_in_a_row, port_range

ROOT = Path(__file__).resolve().parents[1]


def test_ports_are_outside_the_range_the_kernel_hands_out() -> None:
    low, high = map(int, Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    given = [free_port() for _ in range(50)]
    assert len(set(given)) == 50
    assert all(p in port_range() and not low <= p <= high for p in given)


def test_a_port_something_listens_on_is_skipped() -> None:
    free_port()  # the cursor is set
    following = port_range()[ports._cursor[0]]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", following))
        taken.listen()
        assert free_port() != following


def test_another_process_never_gets_a_port_this_one_keeps() -> None:
    mine = [free_port() for _ in range(200)]
    start = port_range().index(min(mine))
    script = (
        "import tests.ports as p\n"
        f"p._cursor.append({start})\n"  # start where this process started
        "print(' '.join(str(p.free_port()) for _ in range(400)))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout
    theirs = {int(p) for p in out.split()}
    assert len(theirs) == 400 and not set(mine) & theirs


def test_ports_in_a_row_are_consecutive_and_free() -> None:
    base = free_ports_in_a_row(3)
    for port in range(base, base + 3):
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))  # free: nothing else has it
    assert free_port() not in range(base, base + 3)
