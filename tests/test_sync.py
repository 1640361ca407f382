"""The blocking facade: same clients, same errors, same types, from several threads at once."""

from __future__ import annotations

import asyncio
import math
import pydoc
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from anyio.from_thread import start_blocking_portal

import plcstack
import plcstack.sync
from plcstack.errors import AddressError, ConnectFailed, OptionError, ValueEncodeError
from plcstack.sim import e71 as sim_e71
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.values import FLOAT32, INT16, KG

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def e71_sim() -> Iterator[Any]:
    """An E71 simulator on a loop of its own thread (the test itself is plain, blocking code)."""
    with start_blocking_portal("asyncio") as portal:
        sim = portal.call(sim_e71.start)
        try:
            yield sim
        finally:
            portal.call(sim.aclose)


def test_blocking_reads_and_writes_with_the_async_types(e71_sim: Any) -> None:
    with plcstack.sync.connect(e71_sim.url, timeout=2) as plc:
        plc.write("D100", [1, 2, 3])
        assert plc.read("D100", 3) == [1, 2, 3]
        plc.write("D103", 7)  # a scalar write
        plc.write_as("D110", FLOAT32, 0.75)
        assert plc.read_as("D110", FLOAT32) == 0.75
        assert plc.read("D110", 2) == [0x0000, 0x3F40]
        plc.write_as("D120", INT16, [-1, -2])
        assert plc.read_as("D120", INT16, 2) == [-1, -2]
        assert plc.call(plc.client.read, "D103", 1) == [7]
        # the same errors, raised in this thread
        with pytest.raises(ValueEncodeError):
            plc.write_as("D130", KG, math.nan)
        with pytest.raises(AddressError, match="D99999"):
            plc.read("D99999")


def test_errors_before_any_thread_and_on_connect() -> None:
    threads = threading.active_count()
    with pytest.raises(OptionError, match="did you mean timeout"):
        plcstack.sync.connect("e71+tcp://127.0.0.1:1", tiemout=3)
    assert threading.active_count() == threads
    with pytest.raises(ConnectFailed), plcstack.sync.connect("e71+tcp://127.0.0.1:1"):
        pass
    assert threading.active_count() == threads  # the helper thread was stopped


def test_safe_from_several_threads(e71_sim: Any) -> None:
    with plcstack.sync.connect(e71_sim.url, timeout=5) as plc:

        def worker(k: int) -> list[int]:
            base = f"D{200 + 10 * k}"
            for i in range(20):
                plc.write(base, [k, i])
                assert plc.read(base, 2) == [k, i]
            return plc.read_as(base, INT16, 2)

        with ThreadPoolExecutor(max_workers=8) as pool:
            results = list(pool.map(worker, range(8)))
        assert results == [[k, 19] for k in range(8)]
        assert plc.client.stats.errors == 0
    with pytest.raises(RuntimeError):
        plc.read("D0")  # closed: the loop thread is gone


def test_help_shows_clients_connect_value_types_and_the_poller() -> None:
    text = pydoc.render_doc(plcstack, renderer=pydoc.plaintext)  # type: ignore[attr-defined]
    for item in (
        "class E71Client",
        "class S5LanClient",
        "class AS511Client",
        "class FetchWriteClient",
        "class Poller",
        "class ValueType",
        "connect(url",
        "KG = <value type kg>",
        "KT = <value type kt>",
    ):
        assert item in text, item


@pytest.mark.parametrize(
    ("ending", "code"),
    [("print('done')", 0), ("raise ValueError('the script failed')", 1)],
    ids=["forgets-close", "raises"],
)
async def test_a_script_that_forgets_close_exits_as_without_plcstack(
    ending: str, code: int
) -> None:
    """Before: the script printed its last line and never exited (the portal's finalizer at
    interpreter exit waited for its own loop thread). Now it ends with its own exit status."""
    memory = MelsecMemory()
    memory.write_words("D", 0, [42])
    sim = await sim_e71.start(memory)
    script = (
        "import plcstack.sync\n"
        f"plc = plcstack.sync.connect({sim.url!r}, timeout=2)\n"
        "print(plc.read('D0', 1))\n"
        f"{ending}\n"
    )
    try:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", script, cwd=ROOT,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            out, err = await asyncio.wait_for(proc.communicate(), 20)
        except TimeoutError:
            proc.kill()
            await proc.wait()
            raise AssertionError("the script did not exit within 20 s") from None
    finally:
        await sim.aclose()
    assert proc.returncode == code, err.decode()
    assert out.decode().startswith("[42]\n")
    if code:
        assert err.decode().rstrip().endswith("ValueError: the script failed")
