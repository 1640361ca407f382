"""tshark and capinfos for the capture tests: the real Wireshark reading our files.

A test that needs tshark and cannot run it fails with the reason (``pytest.fail``), never
skips: a machine without Wireshark must not pass the capture tests silently. Every run is
bounded in time, so a dissector that hung would fail its test, not the suite.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

#: seconds one tshark run may take (a start is about a second on a quiet machine)
TSHARK_TIMEOUT = 60.0


def _binary(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is not installed: the capture tests need Wireshark's {name}")
    return path


def _env(home: Path | None) -> dict[str, str]:
    # a private HOME: no personal Wireshark profile (preferences, plugins) changes what we see
    env = dict(os.environ)
    if home is not None:
        env["HOME"] = str(home)
        env["XDG_CONFIG_HOME"] = str(home / ".config")
    return env


def run_tool(
    name: str, args: Sequence[str], home: Path | None = None, timeout: float = TSHARK_TIMEOUT
) -> subprocess.CompletedProcess[str]:
    """Run a Wireshark tool; its exit status and output are the caller's to check."""
    return subprocess.run(
        [_binary(name), *args],
        capture_output=True,
        text=True,
        errors="backslashreplace",  # a test says what was wrong, not a UnicodeDecodeError
        env=_env(home),
        timeout=timeout,
        check=False,
    )


def tshark(
    args: Sequence[str],
    *,
    home: Path | None = None,
    lua: Sequence[Path] = (),
    timeout: float = TSHARK_TIMEOUT,
) -> str:
    """tshark's standard output; a non-zero exit or a Lua error on stderr fails the test."""
    scripts = [arg for path in lua for arg in ("-X", f"lua_script:{path}")]
    proc = run_tool("tshark", [*scripts, *args], home=home, timeout=timeout)
    errors = "\n".join(
        line for line in proc.stderr.splitlines() if "Running as user" not in line and line
    )
    assert proc.returncode == 0, f"tshark {' '.join(args)} exited {proc.returncode}: {errors}"
    assert "Lua" not in errors and "lua" not in errors, f"tshark reported: {errors}"
    return proc.stdout


def tshark_fields(
    capture: Path,
    fields: Sequence[str],
    *,
    display_filter: str = "",
    options: Sequence[str] = (),
    home: Path | None = None,
    lua: Sequence[Path] = (),
) -> list[list[str]]:
    """One row per displayed packet, one cell per field (several values joined by ``,``)."""
    args = ["-r", str(capture), "-T", "fields", "-E", "separator=\t", "-E", "occurrence=a"]
    for name in fields:
        args += ["-e", name]
    if display_filter:
        args += ["-Y", display_filter]
    out = tshark([*args, *options], home=home, lua=lua)
    return [line.split("\t") for line in out.splitlines()]


def tshark_json(
    capture: Path,
    *,
    display_filter: str = "",
    options: Sequence[str] = (),
    home: Path | None = None,
    lua: Sequence[Path] = (),
) -> list[dict[str, Any]]:
    """tshark's ``-T json`` of the displayed packets."""
    args = ["-r", str(capture), "-T", "json"]
    if display_filter:
        args += ["-Y", display_filter]
    out = tshark([*args, *options], home=home, lua=lua)
    result: list[dict[str, Any]] = json.loads(out or "[]")
    return result


def tshark_value_tables(home: Path, protocols: Sequence[str]) -> dict[str, dict[int, str]]:
    """The value tables tshark has registered for the fields of ``protocols``: field name ->
    value -> text (``tshark -G values``, lines ``V<TAB>field<TAB>value<TAB>text``).

    The report lists every dissector tshark has (about 90 MB, 1.4 million lines): it is kept as
    bytes and searched for our fields' lines, since decoding and splitting all of it line by
    line cost one and a half seconds of CPU for a few hundred lines."""
    proc = subprocess.run(
        [_binary("tshark"), "-G", "values"],
        capture_output=True,
        env=_env(home),
        timeout=TSHARK_TIMEOUT,
        check=False,
    )
    stderr = proc.stderr.decode(errors="backslashreplace")
    assert proc.returncode == 0, f"tshark -G values exited {proc.returncode}: {stderr}"
    report = b"\n" + proc.stdout
    tables: dict[str, dict[int, str]] = {}
    for protocol in protocols:
        key = f"\nV\t{protocol}.".encode()
        at = report.find(key)
        while at >= 0:
            end = report.find(b"\n", at + 1)
            line = report[at + 1 : end if end >= 0 else len(report)]
            parts = line.decode(errors="backslashreplace").split("\t")
            assert len(parts) == 4, f"tshark -G values: a line of {len(parts)} fields: {parts}"
            tables.setdefault(parts[1], {})[int(parts[2], 0)] = parts[3]
            at = report.find(key, end) if end >= 0 else -1
    return tables


def capinfos(capture: Path) -> str:
    proc = run_tool("capinfos", [str(capture)])
    assert proc.returncode == 0, f"capinfos {capture}: {proc.stderr}"
    return proc.stdout
