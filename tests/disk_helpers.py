"""A small disk for the tests of full and failing disks: a tmpfs of a few hundred KiB.

The tests run as root, so ``mount -t tmpfs -o size=256k tmpfs DIR`` gives a file system that
fills after a few hundred messages and reports ENOSPC like a real full disk. Without the
privilege to mount, the test fails with the reason: a full-disk test that silently ran on a
roomy disk would prove nothing.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

__all__ = ["fill", "small_disk"]


@contextlib.contextmanager
def small_disk(directory: Path, size: str = "256k") -> Iterator[Path]:
    """``directory`` (created) with a tmpfs of ``size`` mounted on it, unmounted afterwards."""
    directory.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        pytest.fail(
            f"cannot mount a {size} tmpfs on {directory} for a full-disk test (needs root):"
            f" {done.stderr.strip() or done.returncode}",
            pytrace=False,
        )
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], capture_output=True, check=False)


def fill(directory: Path, name: str = "filler") -> Path:
    """Write a file into ``directory`` until its disk is full; the file (delete it to free the
    space again)."""
    path = directory / name
    block = b"\0" * 4096
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        while True:
            try:
                os.write(fd, block)
            except OSError:
                break
    finally:
        os.close(fd)
    return path
