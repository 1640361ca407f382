"""Supervised sinks and honest exits: a sink failure costs one sample, a dead sink task is
restarted (and /healthz says so meanwhile), and ``plcstack poll`` never ends early with exit 0."""

from __future__ import annotations

import argparse
import asyncio
import io
import logging
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from plcstack.cli.poll import run_poll
from plcstack.north.config import NorthConfig
from plcstack.north.face import FaceBase
from plcstack.north.health import Health
from plcstack.north.metrics import MetricsSettings
from plcstack.north.pipeline import North
from plcstack.north.sparkplug_pb import Payload
from plcstack.north.supervise import Supervisor
from plcstack.poll.config import PollConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.sim import e71, s5lan
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.sim.s5memory import S5Memory
from tests.north_helpers import sample, subscriber
from tests.scan_helpers import scan
from tests.servers import Mosquitto
from tests.test_north_metrics import http

ROOT = Path(__file__).resolve().parent.parent


class PickySink:
    """Cannot take the value 13; says so with a TypeError, as an encoder bug would."""

    name = "picky"

    def __init__(self, probe: bool) -> None:
        self.got: list[list[Sample]] = []
        self.groups: set[str] = set()
        if probe:
            self.probe = self._check

    def _check(self, s: Sample) -> None:
        if s.value == 13:
            raise TypeError("int() argument must be a string, not 'tuple'")

    def submit(self, scans: list[Scan]) -> None:
        samples = [s for scan in scans for s in scan.samples]
        for s in samples:
            self._check(s)
        self.got.append(samples)
        self.groups.update(scan.group for scan in scans)


@pytest.mark.parametrize("probe", [True, False], ids=["probe", "one-by-one"])
def test_a_sample_a_sink_cannot_take_costs_only_that_sample(
    probe: bool, caplog: pytest.LogCaptureFixture
) -> None:
    supervisor = Supervisor()
    sink = PickySink(probe)
    batch = [
        scan(
            sample("press1", "a", 1), sample("press1", "b", 13), sample("press1", "c", 3), group="g"
        )
    ]
    with caplog.at_level(logging.ERROR, "plcstack.north.supervise"):
        supervisor.submit("picky", sink.submit, batch, getattr(sink, "probe", None))
        supervisor.submit("picky", sink.submit, batch, getattr(sink, "probe", None))
    got = [s for b in sink.got for s in b]
    assert [(s.tag, s.value) for s in got] == [("a", 1), ("b", None), ("c", 3)] * 2
    bad = got[1]
    assert bad.quality is Quality.BAD and bad.error is not None
    assert "picky could not take this value: TypeError" in bad.error
    assert supervisor.errors == {"picky": 2}
    assert sink.groups == {"g"}  # what is retried keeps the scan's group
    # logged once (per sink, PLC, tag and kind), naming the PLC and the tag
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1
    assert "picky: PLC press1 tag b: cannot take the value 13 (TypeError" in errors[0]


def test_a_broken_pipe_still_ends_the_run() -> None:
    def emit(batch: list[Scan]) -> None:
        raise BrokenPipeError

    with pytest.raises(BrokenPipeError):
        Supervisor().submit("stdout", emit, [scan(sample("p", "t", 1))])


async def test_a_dead_task_is_restarted_with_backoff_and_reported_meanwhile(
    caplog: pytest.LogCaptureFixture,
) -> None:
    supervisor = Supervisor(initial=0.05, maximum=0.05)
    starts = 0
    running = asyncio.Event()
    reports: list[list[Health]] = []

    async def flaky() -> None:
        nonlocal starts
        starts += 1
        if starts <= 2:
            await asyncio.sleep(0)
            raise RuntimeError(f"crash {starts}")
        running.set()
        await asyncio.Event().wait()

    def note() -> None:
        reports.append(supervisor.health())

    with caplog.at_level(logging.ERROR, "plcstack.north.supervise"):
        handle = supervisor.start("feeder", flaky)
        assert handle.task is not None
        handle.task.add_done_callback(lambda _: asyncio.get_running_loop().call_soon(note))
        async with asyncio.timeout(5):
            await running.wait()
    assert starts == 3 and handle.restarts == 2
    assert reports and [(h.name, h.problem) for h in reports[0]] == [
        ("feeder", "failed (RuntimeError: crash 1); restarting")
    ]
    assert reports[0][0].since is not None
    assert supervisor.health() == []  # running again
    assert supervisor.errors == {"feeder": 2}
    messages = [r.getMessage() for r in caplog.records]
    first = "feeder failed: RuntimeError: crash 1; restarting in"
    assert any(m.startswith(first) for m in messages)
    await supervisor.aclose()
    assert handle.task is not None and handle.task.done()


async def test_healthz_names_a_dead_sink_until_it_runs_again() -> None:
    class Crashing(FaceBase):
        name = "crashing"

        def __init__(self, supervisor: Supervisor) -> None:
            self.supervisor = supervisor

        async def start(self) -> None:
            self.supervisor.start(self.name, self.run)

        async def run(self) -> None:
            raise ConnectionError("lost the broker")

        def submit(self, scans: Sequence[Scan]) -> None:
            pass

    # the restart is far away: /healthz is asked meanwhile
    supervisor = Supervisor(initial=30.0, maximum=30.0)
    poller = Poller(PollConfig((), {"default": 1.0}))  # no PLC, never started
    north = North(
        poller,
        NorthConfig(metrics=MetricsSettings(port=0)),
        faces=[Crashing(supervisor)],
        supervisor=supervisor,
    )
    async with north:
        async with asyncio.timeout(5):
            while not north.supervisor.down:  # noqa: ASYNC110 - waits for a condition
                await asyncio.sleep(0.01)
        assert north.metrics is not None
        status, body = await http(north.metrics.port, b"GET /healthz HTTP/1.0\r\n\r\n")
        metrics = (await http(north.metrics.port, b"GET /metrics HTTP/1.0\r\n\r\n"))[1]
    assert status == 503
    text = body.decode()
    assert text.startswith("crashing: failed (ConnectionError: lost the broker); restarting since ")
    assert text.count("\n") == 1  # every other part is healthy
    assert b'plcstack_sink_errors_total{sink="crashing"} 1.0' in metrics


def _args(config: Path, **more: Any) -> argparse.Namespace:
    values: dict[str, Any] = {
        "config": str(config),
        "format": "jsonl",
        "duration": 30.0,
        "stats_every": None,
        "shard": None,
        "mqtt": None,
        "nats": None,
    }
    values.update(more)
    return argparse.Namespace(**values)


async def test_poll_exits_1_naming_what_failed_when_the_consumer_dies(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    sim = await e71.start(MelsecMemory())
    config = tmp_path / "plant.toml"
    config.write_text(
        f'[poll]\ninterval = 0.05\n[[plc]]\nname = "press1"\nurl = "{sim.url}"\n'
        '[plc.tags]\nstrokes = { address = "D100" }\n'
    )

    async def broken(self: North) -> None:
        raise RuntimeError("the consumer broke")

    monkeypatch.setattr(North, "run", broken)
    try:
        code = await asyncio.wait_for(run_poll(_args(config), out=io.StringIO()), 20)
    finally:
        await sim.aclose()
    err = capsys.readouterr().err
    assert code == 1  # main: 0, as if the run had ended normally
    assert err.splitlines()[-1] == (
        "plcstack: error: poll: the sample consumer failed: RuntimeError: the consumer broke"
    )


def test_poll_with_mqtt_but_without_its_library_exits_2_naming_the_extra(tmp_path: Path) -> None:
    config = tmp_path / "plant.toml"
    config.write_text(
        '[[plc]]\nname = "press1"\nurl = "e71+tcp://127.0.0.1:1"\n'
        '[plc.tags]\nstrokes = { address = "D100" }\n[mqtt]\nurl = "mqtt://127.0.0.1:1"\n'
    )
    script = (
        "import sys; sys.modules['aiomqtt'] = None\n"  # as if the extra were not installed
        "from plcstack.cli import main\n"
        f"sys.exit(main(['poll', {str(config)!r}, '--duration', '5']))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=30
    )
    assert done.returncode == 2, done.stderr  # main: 0 after 5 s of JSON lines, nothing sent
    assert done.stdout == ""
    assert done.stderr.splitlines() == [
        "plcstack: error: poll: [mqtt] needs the Python package aiomqtt, which is not installed:"
        " pip install 'plcstack[mqtt]'"
    ]


async def test_a_sparkplug_value_the_encoder_cannot_take_costs_one_sample_not_the_run(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """A tag whose value the Sparkplug encoder once could not take (a KY tuple): before, the
    sink's TypeError ended the consumer, the run stopped after its first scan with exit 0 and
    no log line. Now every scan of the other tag goes out, and the failure (if the encoder still
    fails) is one ERROR line naming the PLC and the tag. KY is an S5 format: an S5 PLC."""
    memory = S5Memory(default_dbs={10: 8})
    memory.write_db_words(10, 0, [7, 0x0102])
    sim = await s5lan.start(memory)
    config = tmp_path / "plant.toml"
    config.write_text(
        f"""
[poll]
interval = 0.05
[[plc]]
name = "press1"
url = "{sim.url}"
[plc.tags]
strokes = {{ address = "DB10.DW0", type = "uint16" }}
pair = {{ address = "DB10.DW1", type = "ky" }}
[mqtt]
url = "mqtt://{mosquitto.host}:{mosquitto.port}"
mode = "sparkplug"
client_id = "edge-ky"
group_id = "g"
"""
    )
    try:
        async with subscriber(mosquitto.host, mosquitto.port, "spBv1.0/g/DDATA/#") as sub:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "plcstack", "poll", str(config), "--format", "none",
                "--duration", "30", cwd=ROOT, stderr=asyncio.subprocess.PIPE,
            )  # fmt: skip
            try:
                # one DDATA per scan: ten of them are scans after the first (main: none came)
                await sub.wait_for(lambda s: len(s.messages) >= 10, timeout=20)
            finally:
                proc.terminate()
                _, err_bytes = await asyncio.wait_for(proc.communicate(), 20)
    finally:
        await sim.aclose()
    err = err_bytes.decode()
    assert proc.returncode == 0, err  # SIGTERM: the normal end of a service
    names: set[str] = set()
    for _, payload in sub.messages:
        names.update(m.name for m in Payload.FromString(payload).metrics)
    assert "strokes" in names
    if "pair" not in names:  # the encoder cannot take it: said once, by name
        assert err.count("sparkplug: PLC press1 tag pair: cannot take the value") == 1, err
    assert "sparkplug mqtt://" in err and " not delivered" in err  # the sink's summary line


def test_serve_opcua_with_metrics_but_without_its_library_exits_2(tmp_path: Path) -> None:
    config = tmp_path / "plant.toml"
    config.write_text(
        '[[plc]]\nname = "press1"\nurl = "e71+tcp://127.0.0.1:1"\n'
        '[plc.tags]\nstrokes = { address = "D100" }\n[metrics]\nlisten = "127.0.0.1:0"\n'
    )
    script = (
        "import sys; sys.modules['prometheus_client'] = None\n"
        "from plcstack.cli import main\n"
        f"sys.exit(main(['serve', 'opcua', {str(config)!r}, '--duration', '5']))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=30
    )
    assert done.returncode == 2, done.stderr  # main: "internal error" and exit 1
    assert done.stderr.splitlines()[-1] == (
        "plcstack: error: serve opcua: [metrics] needs the Python package prometheus_client,"
        " which is not installed: pip install 'plcstack[metrics]'"
    )
