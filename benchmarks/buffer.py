"""What the store-and-forward queue costs per message, and what a full disk costs.

The queue (:mod:`plcstack.north.buffer`) is on every sink's path: each message is put, peeked
and acknowledged once. Measured here, the process pinned to one CPU, as process CPU time per
message (median of ``--repeats`` rounds, each case once per round in turn):

* ``floor``: the least any FIFO does: a deque append, and a popleft per acknowledgement;
* ``memory``: a queue without a file, the publisher's way (put, then peek 64 and ack them);
* ``disk``: a queue whose file takes the backlog (``memory_bytes`` 64 KiB): a broker outage
  of ``--messages`` spilled to disk, then drained in windows of 64;
* ``full``: the same on a disk that is full (a 256 KiB tmpfs filled first; root only): what a
  put costs while the disk refuses (a write is tried at most once a second).

``--compare REV`` also runs ``memory`` and ``disk`` with the queue module as it was at git
revision REV (loaded from ``git show``), in the same rounds: the ratio new/old is the change's
cost on this machine at this moment.

    python -m benchmarks.buffer [--messages 20000] [--repeats 7] [--compare main]
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import importlib.util
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from plcstack.north import buffer as current

TOPIC = "plcstack/press1/data/default"
PAYLOAD = b'{"plc":"press1","group":"default","timestamp":1800000000000,"values":{"n":1}}'


def pin() -> None:
    """One CPU for this process (the other for whatever else runs), if there are two."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) > 1:
        os.sched_setaffinity(0, {cpus[-1]})


def old_module(rev: str) -> Any:
    """``plcstack/north/buffer.py`` as it was at ``rev``, as a module of its own."""
    source = subprocess.run(
        ["git", "show", f"{rev}:plcstack/north/buffer.py"], capture_output=True, check=True
    ).stdout
    path = Path(tempfile.mkdtemp()) / f"buffer_{rev.replace('/', '_')}.py"
    path.write_bytes(source)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    spec.loader.exec_module(module)
    return module


def cpu(run: Callable[[], int]) -> float:
    """Process CPU microseconds per message of ``run()`` (which returns its message count)."""
    start = time.process_time()
    n = run()
    return (time.process_time() - start) / n * 1e6


def floor(n: int) -> int:
    q: collections.deque[tuple[int, str, bytes]] = collections.deque()
    for i in range(n):
        q.append((i, TOPIC, PAYLOAD))
    while q:
        for _ in range(min(64, len(q))):
            q.popleft()
    return n


def drain(q: Any) -> None:
    while len(q):
        window = q.peek(64)
        q.ack(window[-1].seq)


def in_memory(module: Any, n: int) -> int:
    q = module.StoreAndForward(None, max_bytes=1 << 30)
    for i in range(n):
        q.put(TOPIC, PAYLOAD)
        if i % 64 == 63:
            drain(q)
    drain(q)
    return n


def on_disk(module: Any, n: int, directory: Path) -> int:
    path = directory / f"q{time.monotonic_ns()}.sqlite"
    q = module.StoreAndForward(path, memory_bytes=64 << 10, max_bytes=1 << 30)
    for _ in range(n):
        q.put(TOPIC, PAYLOAD)
    assert q.on_disk > n // 2, "the outage did not reach the disk"
    drain(q)
    q.close()
    for suffix in ("", "-wal", "-shm"):
        with contextlib.suppress(FileNotFoundError):
            Path(f"{path}{suffix}").unlink()
    return n


@contextlib.contextmanager
def full_disk() -> Iterator[Path | None]:
    """A 256 KiB tmpfs, filled; None when it cannot be mounted (not root)."""
    directory = Path(tempfile.mkdtemp())
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(directory)],
        capture_output=True,
        check=False,
    )
    if done.returncode != 0:
        yield None
        return
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], capture_output=True, check=False)


def refused(n: int, directory: Path) -> int:
    """Puts while the disk refuses: a fresh queue per round, the disk full under it."""
    path = directory / "q.sqlite"
    q = current.StoreAndForward(path, memory_bytes=0, max_bytes=1 << 30)
    fd = os.open(directory / "filler", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        with contextlib.suppress(OSError):
            while True:
                os.write(fd, b"\0" * 4096)
    finally:
        os.close(fd)
    for _ in range(n):
        q.put(TOPIC, PAYLOAD)
    assert q.failure is not None, "the disk took the messages: not full"
    drain(q)
    q.close()
    for name in ("filler", "q.sqlite", "q.sqlite-wal", "q.sqlite-shm"):
        with contextlib.suppress(FileNotFoundError):
            (directory / name).unlink()
    return n


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--messages", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--compare", metavar="REV", help="also the queue as it was at REV")
    args = parser.parse_args(argv)
    pin()
    n = args.messages
    old = old_module(args.compare) if args.compare else None
    work = Path(tempfile.mkdtemp(prefix="plcstack-buffer-bench-"))
    logging.getLogger("plcstack.north.buffer").setLevel(logging.CRITICAL)  # the full disk's ERROR
    with full_disk() as full:
        cases: dict[str, Callable[[], int]] = {
            "floor": lambda: floor(n),
            "memory": lambda: in_memory(current, n),
            "disk": lambda: on_disk(current, n, work),
        }
        if old is not None:
            cases["memory (old)"] = lambda: in_memory(old, n)
            cases["disk (old)"] = lambda: on_disk(old, n, work)
        if full is not None:
            cases["full"] = lambda: refused(n, full)
        results: dict[str, list[float]] = {name: [] for name in cases}
        for _ in range(args.repeats):
            for name, run in cases.items():
                results[name].append(cpu(run))
    medians = {name: statistics.median(values) for name, values in results.items()}
    base = medians["floor"]
    print(f"{n} messages of {len(TOPIC) + len(PAYLOAD)} bytes, median of {args.repeats} rounds")
    print(f"{'case':<14} {'us/message':>10} {'x floor':>8}  range")
    for name, value in medians.items():
        spread = f"{min(results[name]):.2f}-{max(results[name]):.2f}"
        print(f"{name:<14} {value:>10.2f} {value / base:>8.1f}  {spread}")
    if old is not None:
        for case in ("memory", "disk"):
            ratio = medians[case] / medians[f"{case} (old)"]
            print(f"{case}: new/old {ratio:.2f}")
    if full is None:
        print("full: not measured (mounting a tmpfs needs root)")


if __name__ == "__main__":
    main()
