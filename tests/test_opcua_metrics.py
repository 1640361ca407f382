"""``plcstack serve opcua`` with ``[metrics]``: /metrics and /healthz from the same collector as
``plcstack poll`` (PLC up, requests, failed-request latencies), and a taken port refused."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from plcstack.cli.serve import run_opcua
from plcstack.poll.config import ConfigError
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.servers import free_port

CONFIG = """
[poll]
interval = 0.05
[opcua]
listen = "127.0.0.1:0"
[metrics]
listen = "127.0.0.1:{port}"
[[plc]]
name = "press1"
url = "{url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16" }}
[[plc]]
name = "dead"
url = "e71+tcp://127.0.0.1:{dead}?timeout=0.2"
[plc.tags]
level = {{ address = "D1", type = "uint16" }}
"""


async def get(port: int, path: str) -> tuple[int, str]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.0\r\n\r\n".encode())
    data = await reader.read()
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body.decode()


def args(path: Path, metrics_port: int | None = None) -> argparse.Namespace:
    return argparse.Namespace(
        config=str(path), duration=None, hash_password=False, metrics_port=metrics_port
    )


@pytest.mark.slow  # an asyncua server starts and stops: about 4 s here
async def test_serve_opcua_serves_metrics_from_the_poll_collector(tmp_path: Path) -> None:
    memory = MelsecMemory()
    memory.write_words("D", 100, [5])
    sim = await e71.start(memory)
    port = free_port()
    path = tmp_path / "plant.toml"
    path.write_text(CONFIG.format(port=port, url=sim.url, dead=free_port()))
    serving = asyncio.create_task(run_opcua(args(path)))
    try:
        families: dict[str, Any] = {}
        async with asyncio.timeout(20):
            while True:  # until the poller has news of both PLCs
                await asyncio.sleep(0.1)
                assert not serving.done(), serving.result()
                try:
                    status, text = await get(port, "/metrics")
                except OSError:
                    continue  # not listening yet
                families = {f.name: f for f in text_string_to_metric_families(text)}
                up = {s.labels["plc"]: s.value for s in families["plcstack_plc_up"].samples}
                failed = families["plcstack_failed_request_latency_seconds"].samples
                if up == {"press1": 1.0, "dead": 0.0} and failed:
                    break
        assert status == 200
        requests = {s.labels["plc"]: s.value for s in families["plcstack_requests"].samples}
        assert requests["press1"] >= 1
        kinds = {(s.labels["plc"], s.labels["error"]) for s in failed}
        assert kinds == {("dead", "ConnectFailed")}
        status, health = await get(port, "/healthz")
        assert status == 200 and health.splitlines()[0] == "ok", health
        assert "opcua: ok, 2 variables" in health.splitlines()  # every face of the run
        os.kill(os.getpid(), signal.SIGTERM)  # the command's own handler: a clean stop
        assert await asyncio.wait_for(serving, 15) == 0
    finally:
        if not serving.done():
            serving.cancel()
            await asyncio.gather(serving, return_exceptions=True)
        await sim.aclose()
    with pytest.raises(OSError):
        await get(port, "/metrics")  # stopped with the command


async def test_a_taken_metrics_port_is_a_config_error_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(CONFIG.format(port=0, url="e71+tcp://127.0.0.1:1", dead=1))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=f"cannot serve /metrics on 127.0.0.1:{busy}"):
            await run_opcua(args(path, metrics_port=busy))
