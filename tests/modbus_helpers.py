"""An independent Modbus client for the server's tests: libmodbus, through tests/modbus_client.c.

The C program is compiled once per test session into a temporary directory. A machine without
gcc or libmodbus (Debian: ``libmodbus-dev``, installed by ``scripts/setup-test-machine``) makes
the tests that need it *fail* with the reason, never skip.
"""

from __future__ import annotations

import asyncio
import shutil
import subprocess
import tempfile
from pathlib import Path

SOURCE = Path(__file__).with_name("modbus_client.c")
_built: Path | None = None


class ClientUnavailable(RuntimeError):
    """The libmodbus client cannot be built here (the message says why)."""


def modbus_client() -> Path:
    """The compiled client (built on first use)."""
    global _built
    if _built is not None:
        return _built
    gcc = shutil.which("gcc") or shutil.which("cc")
    if gcc is None:
        raise ClientUnavailable("no C compiler (gcc) to build the libmodbus test client")
    flags = ["-I/usr/include/modbus", "-lmodbus"]
    pkg_config = shutil.which("pkg-config")
    if pkg_config is not None:
        found = subprocess.run(
            [pkg_config, "--cflags", "--libs", "libmodbus"], capture_output=True, text=True
        )
        if found.returncode == 0:
            flags = found.stdout.split()
    target = Path(tempfile.mkdtemp(prefix="plcstack-modbus-")) / "modbus_client"
    built = subprocess.run(
        [gcc, "-O2", "-o", str(target), str(SOURCE), *flags], capture_output=True, text=True
    )
    if built.returncode != 0:
        raise ClientUnavailable(
            "cannot build the libmodbus test client (apt-get install libmodbus-dev):\n"
            + built.stderr
        )
    _built = target
    return target


async def modbus(endpoint: str, *commands: str | int, unit: int = 1) -> list[str]:
    """Run requests through libmodbus against ``host:port``; one answer line per request
    (``"ok 1 2"``, ``"exc 0x02"``, ``"err ..."``)."""
    host, _, port = endpoint.rpartition(":")
    proc = await asyncio.create_subprocess_exec(
        str(modbus_client()),
        host,
        port,
        str(unit),
        *(str(c) for c in commands),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), 30)
    if proc.returncode != 0:
        raise AssertionError(f"modbus client exited {proc.returncode}: {err.decode()}")
    return out.decode().splitlines()
