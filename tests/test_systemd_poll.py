"""``plcstack poll`` (and ``sim``, ``gateway``) as systemd runs it: ``NOTIFY_SOCKET`` and
``WATCHDOG_USEC`` in its environment, a stand-in of systemd's socket (tests/systemd_helpers.py)
listening.

One run, in the order a service lives it: READY only after both PLCs had their first scan (one
answers, one refuses the connection), with the status naming the offline one; watchdog pings at
half the asked interval; SIGHUP between RELOADING=1 (dated) and READY=1, also when the reload
adds a PLC (READY=1 once it is applied) and when the file no longer loads (the run goes on);
SIGTERM says STOPPING=1 and the run ends with 0.
"""

from __future__ import annotations

import asyncio
import itertools
import os
import re
import signal
import sys
import time
from pathlib import Path

from plcstack.sim import as511 as sim_as511
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.systemd.notify import monotonic_usec
from tests.systemd_helpers import NotifySocket, two_plcs

ROOT = Path(__file__).resolve().parent.parent


async def test_poll_under_systemd(tmp_path: Path) -> None:
    sim = await e71.start(MelsecMemory())
    config = two_plcs(tmp_path, sim.url, 0.1)
    with NotifySocket(tmp_path) as sock:
        env = {**os.environ, "NOTIFY_SOCKET": sock.address, "WATCHDOG_USEC": "600000"}
        started = time.monotonic()
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "-v", "poll", str(config), "--format", "none",
            "--duration", "60", cwd=ROOT, env=env, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            ready = await sock.arrival("READY", timeout=20)
            assert ready.fields == (
                ("READY", "1"),
                ("STATUS", "2 PLCs: 1 online, 1 offline (oven2)"),
            )
            # the watchdog: 600 ms asked, a ping every 300 ms
            await asyncio.sleep(1.0)
            pings = [m.at for m in sock.with_field("WATCHDOG")]
            gaps = [b - a for a, b in itertools.pairwise(pings)]
            assert pings[0] > started and len(pings) >= 3, gaps
            assert max(gaps) < 0.6, gaps

            hangup = time.monotonic()
            before = monotonic_usec()
            proc.send_signal(signal.SIGHUP)
            reloading = await sock.arrival("RELOADING", after=hangup)
            assert reloading.names[:2] == ["RELOADING", "MONOTONIC_USEC"]
            assert int(reloading.get("MONOTONIC_USEC") or 0) >= before
            # sd_notify(3): RELOADING=1 carries CLOCK_MONOTONIC in µs of when the reload began
            assert int(reloading.get("MONOTONIC_USEC") or 0) <= reloading.at * 1e6
            again = await sock.arrival("READY", after=reloading.at)
            assert again.get("STATUS") == "2 PLCs: 1 online, 1 offline (oven2)"

            # a reload that changes something: READY=1 only once it is applied (the status
            # counts the added PLC), and nothing says READY=1 between the two
            text = config.read_text()
            press1 = "[[plc]]" + text.split("[[plc]]")[1]
            config.write_text(text + press1.replace('"press1"', '"kiln3"'))
            hangup = time.monotonic()
            proc.send_signal(signal.SIGHUP)
            reloading = await sock.arrival("RELOADING", after=hangup)
            applied = await sock.arrival("READY", after=reloading.at)
            assert (applied.get("STATUS") or "").startswith("3 PLCs: "), applied
            assert [m for m in sock.with_field("READY") if m.at > reloading.at] == [applied]

            config.write_text("[[plc]]\nname = 'x'\n")  # no url: does not load
            hangup = time.monotonic()
            proc.send_signal(signal.SIGHUP)
            reloading = await sock.arrival("RELOADING", after=hangup)
            failed = await sock.arrival("READY", after=reloading.at)
            assert (failed.get("STATUS") or "").startswith("reload failed, running as before: ")
            assert "url" in (failed.get("STATUS") or "")
            await sock.arrival("WATCHDOG", after=failed.at)  # it runs on

            term = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            stopping = await sock.arrival("STOPPING", after=term)
            assert stopping.fields == (("STOPPING", "1"), ("STATUS", "stopping"))
            _, err = await asyncio.wait_for(proc.communicate(), 20)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            await sim.aclose()
    text = err.decode()
    assert proc.returncode == 0, text
    assert "does not load, nothing changed" in text
    assert "reload (SIGHUP): PLCs added: none; removed: none; changed: none" in text
    assert "reload (SIGHUP): PLCs added: kiln3; removed: none; changed: none" in text


async def _ready_then_stopping(tmp_path: Path, *args: str) -> tuple[str, str]:
    """Run ``plcstack ARGS`` under a notify socket: the READY status, and the STOPPING message
    after SIGTERM (which must end the command with 0)."""
    with NotifySocket(tmp_path) as sock:
        env = {**os.environ, "NOTIFY_SOCKET": sock.address, "PYTHONPATH": str(ROOT)}
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", *args, cwd=ROOT, env=env,
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            ready = await sock.arrival("READY", timeout=20)
            proc.send_signal(signal.SIGTERM)
            stopping = await sock.arrival("STOPPING", after=ready.at)
            _, err = await asyncio.wait_for(proc.communicate(), 20)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    assert proc.returncode == 0, err.decode()
    return ready.get("STATUS") or "", ",".join(stopping.names)


async def test_sim_under_systemd(tmp_path: Path) -> None:
    status, stopping = await _ready_then_stopping(tmp_path, "sim", "e71", "--port", "0")
    assert re.fullmatch(r"sim e71: listening on 127\.0\.0\.1:\d+ \(TCP\)", status), status
    assert stopping == "STOPPING,STATUS"


async def test_gateway_under_systemd(tmp_path: Path) -> None:
    async with await sim_as511.start() as sim:
        status, stopping = await _ready_then_stopping(
            tmp_path, "gateway", sim.url, "--s5lan", "0", "--duration", "20"
        )
    assert re.fullmatch(
        rf"gateway to {re.escape(sim.url)}: s5lan listening on 127\.0\.0\.1:\d+ \(TCP\)", status
    ), status
    assert stopping == "STOPPING,STATUS"
