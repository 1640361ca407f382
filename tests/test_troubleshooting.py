"""docs/troubleshooting.md is checked against the real error texts.

Every row's message is produced here by making the mistake the row names, and every mistake
made here has its row: a message reworded in the code fails this test until the page follows.
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

import plcstack
from plcstack.config import load_config
from plcstack.errors import PlcError
from plcstack.sim import e71
from tests.cli_helpers import cli_in_process

PAGE = Path(__file__).resolve().parents[1] / "docs" / "troubleshooting.md"
NOWHERE = "127.0.0.1:9"


def _rows() -> list[str]:
    text = PAGE.read_text(encoding="utf-8")
    return re.findall(r"^\| `([^`]+)` \|", text, re.MULTILINE)


async def _plc_error(url: str, call: Callable[[plcstack.Client], Awaitable[object]]) -> str:
    try:
        async with plcstack.connect(url, timeout=0.5, connect_timeout=1) as plc:
            await call(plc)
    except PlcError as exc:
        return str(exc)
    raise AssertionError("no error")


async def _cannot_connect() -> str:
    return await _plc_error(f"e71+tcp://{NOWHERE}", lambda plc: plc.read("D0", 1))


async def _silent_port() -> str:
    server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        return await _plc_error(f"s5lan://127.0.0.1:{port}", lambda plc: plc.read("DB10.DW0", 1))
    finally:
        server.close()


async def _e71_behind_s5_url() -> str:
    async with await e71.start() as sim:
        url = sim.url.replace("e71+tcp://", "s5lan://")
        return await _plc_error(url, lambda plc: plc.read("DB10.DW0", 1))


async def _ninth_e71_client() -> str:
    async with await e71.start() as sim:
        held = [plcstack.connect(sim.url) for _ in range(8)]
        try:
            for plc in held:
                await plc.aopen()
            return await _plc_error(sim.url, lambda plc: plc.read("D0", 1))
        finally:
            for plc in held:
                await plc.aclose()


async def _write_a_float() -> str:
    plc = plcstack.connect(f"e71+tcp://{NOWHERE}")  # refused before any connection is made
    try:
        await plc.write("D0", 1.5)  # type: ignore[arg-type]
    except PlcError as exc:
        return str(exc)
    finally:
        await plc.aclose()
    raise AssertionError("no error")


async def _cli_error(*argv: str) -> str:
    code, _, err = await cli_in_process(*argv)
    assert code == 2, err
    return err


async def _config_typo(tmp: Path) -> str:
    path = tmp / "plant.toml"
    path.write_text(
        '[[plc]]\nname = "a"\nurl = "e71+tcp://h:5000"\ntags = { t = { adress = "D0" } }\n'
    )
    with pytest.raises(PlcError) as err:
        load_config(path)
    return str(err.value)


async def _config_error(tmp: Path, text: str) -> str:
    path = tmp / "names.toml"
    path.write_text(text)
    with pytest.raises(PlcError) as err:
        load_config(path)
    return str(err.value)


async def _config_warning(tmp: Path) -> str:
    path = tmp / "shared.toml"
    plc = '[[plc]]\nname = "p{}"\nurl = "s5lan://10.0.0.7:5010"\ntags = {{ t = "DB1.DW0" }}\n'
    path.write_text(plc.format(1) + plc.format(2))
    (said,) = load_config(path).notices
    return said


def _mistakes(tmp: Path) -> dict[str, Awaitable[str]]:
    return {
        "connect: cannot connect to": _cannot_connect(),
        "sent nothing; an S5-LAN module answers every 26-byte request block": _silent_port(),
        "looks like it comes from a MELSEC E71": _e71_behind_s5_url(),
        "an E71 serves 8 connections at once": _ninth_e71_client(),
        "that is Siemens S5 notation": _cli_error("read", f"e71+tcp://{NOWHERE}", "DB10.DW0"),
        "is not an S5 address but MELSEC notation": _cli_error(
            "read", f"s5lan://{NOWHERE}", "D100"
        ),
        "a bit operand is not a point": _cli_error("read", f"s5lan://{NOWHERE}", "M10.3"),
        "takes a hexadecimal (0-9, A-F) device number": _cli_error(
            "read", f"e71+tcp://{NOWHERE}", "X1G"
        ),
        "unknown value type": _cli_error("read", f"e71+tcp://{NOWHERE}", "D0", "--type", "int64"),
        "cannot be written as points": _write_a_float(),
        "must be a finite number of seconds greater than 0": _cli_error(
            "read", f"e71+tcp://{NOWHERE}", "D0", "--timeout", "0"
        ),
        "did you mean": _config_typo(tmp),
        "may not contain / + #": _config_error(
            tmp, '[[plc]]\nname = "line1/press"\nurl = "e71+tcp://h:5000"\ntags = { t = "D0" }\n'
        ),
        "and this is a MELSEC PLC, whose words hold no S5 formats": _config_error(
            tmp,
            '[[plc]]\nname = "p"\nurl = "e71+tcp://h:5000"\ntags = { t = { address = "D0",'
            ' type = "kg" } }\n',
        ),
        "cannot connect. Make them one [[plc]]": _config_warning(tmp),
    }


async def test_every_row_is_a_real_message_and_every_mistake_has_a_row(tmp_path: Path) -> None:
    mistakes = _mistakes(tmp_path)
    rows = _rows()
    try:
        assert sorted(rows) == sorted(mistakes)
        for fragment, produce in mistakes.items():
            message = await produce
            assert fragment in message, f"{fragment!r} not in {message!r}"
    finally:
        for pending in mistakes.values():
            if asyncio.iscoroutine(pending):
                pending.close()
