"""One run through the faults a plant sees, end to end (slow): the PLC's simulator killed and
restarted on its port, the broker restarted, the poller stopped with SIGTERM and started again.
Every sample the poller took must reach a persistent subscriber at least once and in order, and
neither poller run may stop early or quietly.

Not covered here: a sink crash inside the poller process (tests/test_supervise.py injects one in
process, with its restart and /healthz)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import signal
import sys
from pathlib import Path

import pytest

from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.north_helpers import Subscriber, subscriber
from tests.servers import Mosquitto, free_port

ROOT = Path(__file__).resolve().parent.parent


def _distinct(sub: Subscriber) -> list[dict[str, object]]:
    """Data messages in arrival order, redeliveries (identical payloads) removed."""
    seen: set[bytes] = set()
    out = []
    for topic, payload in sub.messages:
        if "/data/" in topic and payload not in seen:
            seen.add(payload)
            out.append(json.loads(payload))
    return out


def _samples(stderr: str) -> int:
    """The 'samples' column of the poller's statistics table for press1."""
    row = next(line for line in stderr.splitlines() if line.startswith("press1 "))
    return int(row.split()[6])


@pytest.mark.slow
async def test_sim_broker_and_poller_restarts_lose_no_sample(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    memory = MelsecMemory()
    port = free_port()
    sim = await e71.start(memory, port=port)
    config = tmp_path / "plant.toml"
    config.write_text(
        f"""
[poll]
interval = 0.05
[[plc]]
name = "press1"
url = "{sim.url}"
timeout = 0.3
connect_timeout = 0.3
backoff_max = 0.2
[plc.tags]
n = {{ address = "D0", type = "uint16" }}
[mqtt]
url = "mqtt://{mosquitto.host}:{mosquitto.port}"
client_id = "fault-e2e"
buffer_path = "queue.sqlite"
reconnect_max = 0.2
"""
    )

    async def counting() -> None:
        n = 0
        while True:
            n = (n + 1) & 0xFFFF
            memory.write_words("D", 0, [n])
            await asyncio.sleep(0.01)

    async def poller() -> asyncio.subprocess.Process:
        return await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
            "--duration", "60", cwd=ROOT, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip

    async def stop(proc: asyncio.subprocess.Process) -> str:
        proc.send_signal(signal.SIGTERM)
        _, err = await asyncio.wait_for(proc.communicate(), 20)
        text = err.decode()
        assert proc.returncode == 0, text  # SIGTERM: a normal end, never an early one
        assert "error:" not in text, text
        return text

    counter = asyncio.create_task(counting())
    errs: list[str] = []
    try:
        async with subscriber(mosquitto.host, mosquitto.port, "plcstack/#", "e2e") as sub:

            def data(s: Subscriber) -> int:
                return len(_distinct(s))

            proc = await poller()
            await sub.wait_for(lambda s: data(s) >= 20, 20)
            # 1. the PLC goes away (bad samples are published too) and comes back on its port
            await sim.aclose()
            await sub.wait_for(lambda s: "errors" in _distinct(s)[-1], 10)
            sim = await e71.start(memory, port=port)
            await sub.wait_for(lambda s: "values" in _distinct(s)[-1], 10)
            # 2. the broker restarts: the poller queues meanwhile and sends the backlog first
            mark = data(sub)
            mosquitto.stop()
            await asyncio.sleep(0.5)
            mosquitto.start()
            await sub.wait_for(lambda s: data(s) >= mark + 20, 20)
            # 3. the poller is stopped and started again with the same disk queue
            errs.append(await stop(proc))
            proc = await poller()
            mark = data(sub)
            await sub.wait_for(lambda s: data(s) >= mark + 20, 20)
            errs.append(await stop(proc))
            taken = sum(_samples(e) for e in errs)
            await sub.wait_for(lambda s: data(s) >= taken, 20)
            received = _distinct(sub)
    finally:
        counter.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await counter
        await sim.aclose()
    # nothing lost: every sample the two runs took arrived (one tag: one message per scan)
    assert len(received) == taken
    # in order: scan times only grow, across the outages and the restart
    times = [int(str(m["timestamp"])) for m in received]
    assert times == sorted(times)
    # the stop said what it left: nothing waiting at the end of the second run
    assert re.search(r"mqtt mqtt://\S+: \d+ sent, 0 not delivered", errs[1]), errs[1]
    print(f"fault e2e: {taken} samples taken in two runs, {len(received)} received, 0 lost")
