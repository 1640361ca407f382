"""A whole ``plcstack poll`` run writing to a real InfluxDB that goes away for 10 s.

20 simulated PLCs polled at 1 Hz; influxd stopped 6 s into the run and started again 10 s later.
The run's own JSON lines on stdout are the record of every sample it took; afterwards every one
of them is in the database, once (the query compares them per PLC, second by second), and the
run's statistics on stderr say how many lines were held through the outage and replayed.
"""

from __future__ import annotations

import asyncio
import json
import re
import signal
import sys
import time
import urllib.parse
from datetime import datetime
from pathlib import Path

import pytest

from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.servers import Influxd

ROOT = Path(__file__).resolve().parent.parent
PLCS = 20
OUTAGE = 10.0


def micros(iso: str) -> int:
    when = datetime.fromisoformat(iso.replace("Z", "+00:00"))
    return round(when.timestamp() * 1e6)


@pytest.mark.slow
async def test_influx_outage_of_ten_seconds_loses_nothing(influxd: Influxd, tmp_path: Path) -> None:
    influxd.create_database("plant")
    sims = [await e71.start(MelsecMemory()) for _ in range(PLCS)]
    plcs = "".join(
        f'[[plc]]\nname = "press{i}"\nurl = "{sim.url}"\n[plc.tags]\nstrokes = {{address = "D0"}}\n'
        for i, sim in enumerate(sims)
    )
    config = tmp_path / "plant.toml"
    config.write_text(
        f"[poll]\ninterval = 1.0\n{plcs}"
        f'[influx]\nurl = "{influxd.url}"\ndatabase = "plant"\nreconnect_max = 1.0\n'
        f'buffer_path = "{tmp_path / "influx.sqlite"}"\n'
    )
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "plcstack", "poll", str(config), "--format", "jsonl",
        cwd=ROOT, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        await asyncio.sleep(6)
        await asyncio.to_thread(influxd.stop)
        stopped = time.time()
        await asyncio.sleep(OUTAGE)
        await asyncio.to_thread(influxd.start)
        await asyncio.sleep(6)
        proc.send_signal(signal.SIGTERM)
        out, err = await asyncio.wait_for(proc.communicate(), 30)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        for sim in sims:
            await sim.aclose()
    text = err.decode()
    assert proc.returncode == 0, text
    taken: dict[str, list[int]] = {}
    for line in out.decode().splitlines():
        sample = json.loads(line)
        assert sample["quality"] == "good", sample
        taken.setdefault(sample["plc"], []).append(micros(sample["source_time"]))
    assert len(taken) == PLCS
    status, body = influxd.request(
        "GET", "/query?db=plant&q=" + urllib.parse.quote('SELECT strokes FROM plc GROUP BY "plc"')
    )
    assert status == 200, body
    stored = {
        s["tags"]["plc"]: [micros(row[0]) for row in s["values"]]
        for s in json.loads(body)["results"][0]["series"]
    }
    for plc, times in taken.items():
        # every second of every PLC, once: the same times (to the microsecond InfluxDB keeps)
        assert len(stored[plc]) == len(times), plc
        assert all(abs(a - b) <= 1 for a, b in zip(sorted(stored[plc]), sorted(times), strict=True))
        during = [t for t in times if stopped * 1e6 < t < (stopped + OUTAGE) * 1e6]
        assert len(during) >= OUTAGE - 2, (plc, len(during))  # the outage was polled through
    summary = next(line for line in text.splitlines() if line.startswith("influx "))
    found = re.search(r"(\d+) lines written, (\d+) held .* and (\d+) of them replayed", summary)
    assert found, summary
    written, held, replayed = map(int, found.groups())
    total = sum(len(t) for t in taken.values())
    assert written == total
    assert held == replayed and held >= PLCS * (OUTAGE - 2), summary
    assert " 0 rejected by InfluxDB, 0 not delivered" in summary
    print(f"influx outage: {total} lines, {held} held and replayed; {summary}")
