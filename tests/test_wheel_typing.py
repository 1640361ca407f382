"""The typing users see: build the wheel, install it into a fresh venv, run ``mypy --strict`` on
a user's script and check the types mypy reveals (py.typed must ship, read_as must be typed)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

USER_SNIPPET = """\
from typing import reveal_type

import plcstack
import plcstack.sync
from plcstack.values import BOOL, INT16, KG


async def poll() -> None:
    async with plcstack.connect("s5lan://127.0.0.1:5010", timeout=2) as plc:
        word = await plc.read_as("DB10.DW0", INT16)
        real = await plc.read_as("DB10.DW2", KG)
        bit = await plc.read_as("DB10.DW4.3", BOOL)
        words = await plc.read("DB10.DW0", 4)
        reals = await plc.read_as("DB10.DW2", KG, 3)
        reveal_type(word)
        reveal_type(real)
        reveal_type(bit)
        reveal_type(words)
        reveal_type(reals)
        await plc.write_as("DB10.DW2", KG, 1.5)


def script() -> None:
    with plcstack.sync.connect("e71+tcp://127.0.0.1:5000") as plc:
        reveal_type(plc.read_as("D100", KG))
        reveal_type(plc.read_as("D100.3", BOOL))
"""

EXPECTED = [
    "int",  # read_as("DB10.DW0", INT16)
    "float",  # read_as("DB10.DW2", KG)
    "bool",  # read_as("DB10.DW4.3", BOOL)
    "list[int] | list[bool]",  # read("DB10.DW0", 4)
    "list[float]",  # read_as("DB10.DW2", KG, 3)
    "float",  # sync: read_as("D100", KG)
    "bool",  # sync: read_as("D100.3", BOOL)
]


@pytest.mark.slow
def test_wheel_ships_types_that_mypy_strict_sees(tmp_path: Path) -> None:
    # Build from a copy: a build writes build/ and *.egg-info next to pyproject.toml.
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (ROOT / name).exists():
            shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "plcstack", src / "plcstack",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    # Nothing of the test run may leak in: PYTHONPATH=. would make pip and mypy see the tree.
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MYPYPATH")}
    wheels = tmp_path / "wheels"
    subprocess.run(
        # isolated build: pyproject's setuptools>=77 comes from PyPI, as in any user's build
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(src)],
        check=True, env=env,
    )  # fmt: skip
    (wheel,) = wheels.glob("plcstack-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "plcstack/py.typed" in names
    assert "plcstack/values/__init__.py" in names
    # the Lua dissectors `plcstack wireshark` writes (package data in a folder of their own)
    lua = ("common", "melsec1e", "s5lan", "as511", "tanimk")
    assert {f"plcstack/wire/lua/{name}.lua" for name in lua} <= set(names)

    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False).create(env_dir)
    python = env_dir / "bin" / "python"
    # --no-deps: the test must not need the network; mypy reads plcstack from this venv only
    subprocess.run(
        [str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
        check=True, env=env,
    )  # fmt: skip
    site = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True, capture_output=True, text=True, env=env,
    ).stdout.strip()  # fmt: skip
    assert (Path(site) / "plcstack" / "py.typed").is_file()

    user = tmp_path / "user" / "script.py"
    user.parent.mkdir()
    user.write_text(USER_SNIPPET, encoding="utf-8")
    result = subprocess.run(
        [sys.executable, "-m", "mypy", "--strict", "--no-incremental",
         "--python-executable", str(python), "--config-file", "/dev/null", str(user)],
        capture_output=True, text=True, cwd=user.parent, env=env,
    )  # fmt: skip
    revealed = re.findall(r'Revealed type is "([^"]+)"', result.stdout)
    assert result.returncode == 0, result.stdout + result.stderr
    assert revealed == EXPECTED, result.stdout
