"""``plcstack systemd-unit CONFIG``: the unit grants what the file needs and nothing more, and
systemd's own checker (``systemd-analyze verify``, from Debian's ``systemd`` package) takes it
without a word: that command exits 0 even for a line it cannot parse, so its silence is the
check. ``systemd-analyze security --offline`` rates the hardening.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from plcstack.cli import main
from plcstack.cli.systemd import unit_text

ANALYZE = shutil.which("systemd-analyze")

PLC = (
    '[[plc]]\nname = "press1"\nurl = "e71+tcp://10.0.0.5:5000"\n[plc.tags]\nx = {address = "D0"}\n'
)


def analyze(*args: str) -> subprocess.CompletedProcess[str]:
    if ANALYZE is None:
        pytest.fail(
            "systemd-analyze is not installed (Debian: systemd; scripts/setup-test-machine)"
        )
    return subprocess.run([ANALYZE, *args], capture_output=True, text=True, timeout=60)


def verified(tmp_path: Path, text: str, name: str = "plcstack-plant.service") -> str:
    unit = tmp_path / name
    unit.write_text(text)
    done = analyze("verify", "--man=no", str(unit))
    assert (done.returncode, done.stdout + done.stderr) == (0, ""), text
    return text


def lines(text: str, key: str) -> list[str]:
    return [line.split("=", 1)[1] for line in text.splitlines() if line.startswith(key + "=")]


def test_a_plain_file_writes_nowhere_and_has_no_devices(tmp_path: Path) -> None:
    config = tmp_path / "plant.toml"
    config.write_text("[poll]\ninterval = 1.0\n" + PLC)
    text = verified(tmp_path, unit_text(str(config), user="plcstack", watchdog=30))
    assert lines(text, "Type") == ["notify"]
    assert lines(text, "ExecStart") == [f"{sys.executable} -m plcstack poll --format none {config}"]
    assert lines(text, "ExecReload") == ["/bin/kill -HUP $MAINPID"]
    assert lines(text, "Restart") == ["on-failure"]
    assert lines(text, "WatchdogSec") == ["30s"]
    # the first scan of a PLC ends within 2 x (1 s + 2 s timeout + 3 s connect), and 30 s more
    assert lines(text, "TimeoutStartSec") == ["42s"]
    assert lines(text, "NoNewPrivileges") == ["yes"]
    assert lines(text, "ProtectSystem") == ["strict"]
    assert lines(text, "PrivateDevices") == ["yes"]
    assert lines(text, "CapabilityBoundingSet") == [""]
    assert lines(text, "ReadWritePaths") == lines(text, "StateDirectory") == []
    assert lines(text, "User") == lines(text, "Group") == ["plcstack"]


def test_write_access_where_the_paths_point(tmp_path: Path) -> None:
    config = tmp_path / "plant.toml"
    config.write_text(
        PLC
        + '[mqtt]\nurl = "mqtt://127.0.0.1:1883"\nbuffer_path = "/var/lib/plcstack/mqtt.sqlite"\n'
        'state_path = "/var/lib/plcstack/spb/bdseq.json"\n'
        '[audit]\npath = "audit/writes.jsonl"\n'
        '[history]\npath = "/var/lib/plcstack/history.sqlite"\n'
        '[influx]\nurl = "http://127.0.0.1:8086"\ndatabase = "plant"\n'
        'buffer_path = "/var/lib/plcstack-influx/queue.sqlite"\n'
    )
    text = verified(tmp_path, unit_text(str(config), user="gw", watchdog=0))
    assert lines(text, "StateDirectory") == ["plcstack plcstack/spb plcstack-influx"]
    # a relative path is the file's directory's
    assert lines(text, "ReadWritePaths") == [str(tmp_path / "audit")]
    assert lines(text, "WatchdogSec") == []
    assert "# no watchdog (--watchdog 0)" in text


def test_serial_ports_and_low_ports(tmp_path: Path) -> None:
    config = tmp_path / "plant.toml"
    config.write_text(
        '[[plc]]\nname = "kiln"\nurl = "as511:///dev/ttyS0"\n'
        '[plc.tags]\nt = { address = "DB1.DW0" }\n'
        '[[plc]]\nname = "oven"\nurl = "as511:///dev/ttyUSB1?baud=9600"\n'
        '[plc.tags]\nt = { address = "DB1.DW0", modbus = "hr:0" }\n'
        '[modbus]\nendpoint = "0.0.0.0:502"\n'
    )
    text = verified(tmp_path, unit_text(str(config), user="plcstack", watchdog=30))
    assert lines(text, "PrivateDevices") == ["no"]
    assert lines(text, "DevicePolicy") == ["closed"]
    assert lines(text, "DeviceAllow") == ["/dev/ttyS0 rw", "/dev/ttyUSB1 rw"]
    assert lines(text, "SupplementaryGroups") == ["dialout"]
    assert lines(text, "CapabilityBoundingSet") == ["CAP_NET_BIND_SERVICE"]
    assert lines(text, "AmbientCapabilities") == ["CAP_NET_BIND_SERVICE"]


def test_spaces_percent_and_dollar_are_written_for_systemd(tmp_path: Path) -> None:
    folder = tmp_path / "plant 100% $HOME"
    folder.mkdir()
    config = folder / "line 1.toml"
    config.write_text(PLC + '[audit]\npath = "audit log/writes.jsonl"\n')
    text = verified(tmp_path, unit_text(str(config), user="plcstack", watchdog=30))
    quoted = str(folder).replace("%", "%%").replace("$", "$$")
    assert lines(text, "ExecStart")[0].endswith(f' "{quoted}/line 1.toml"')
    assert lines(text, "ReadWritePaths") == [f'"{quoted}/audit log"']
    # a description knows no $ variables, only % specifiers
    described = str(folder).replace("%", "%%")
    assert lines(text, "Description") == [f"plcstack: 1 PLC of {described}/line 1.toml"]


def test_the_hardening_rates_ok(tmp_path: Path) -> None:
    config = tmp_path / "plant.toml"
    config.write_text(PLC)
    unit = tmp_path / "plcstack-plant.service"
    unit.write_text(unit_text(str(config), user="plcstack", watchdog=30))
    done = analyze("security", "--offline=true", "--no-pager", str(unit))
    found = re.search(r"Overall exposure level for \S+: (\d+\.\d+) (\w+)", done.stdout)
    assert found, done.stdout + done.stderr
    # systemd's scale: 0 (locked down) .. 10 (unprotected); "OK" is below 4.5
    assert float(found[1]) <= 3.0 and found[2] == "OK", found[0]


def test_the_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "plant.toml"
    config.write_text(PLC)
    assert main(["systemd-unit", str(config), "--user", "plc-gw", "--watchdog", "12.5"]) == 0
    out = capsys.readouterr().out
    assert out == unit_text(str(config), user="plc-gw", watchdog=12.5)
    assert lines(out, "WatchdogSec") == ["12.5s"]
    assert f"plcstack systemd-unit {config} > plcstack-plant.service" in out
    config.write_text("[[plc]]\nname = 'x'\n")
    assert main(["systemd-unit", str(config)]) == 2
    assert capsys.readouterr().err.endswith(f" ({config}:1)\n")
    config.write_text(PLC)
    assert main(["systemd-unit", str(tmp_path / "plant.toml"), "--user", "a b"]) == 2
    assert main(["systemd-unit", str(tmp_path / "plant.toml"), "--watchdog", "-1"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "plcstack: error: systemd-unit: a user name has no spaces and is not empty: 'a b'",
        "plcstack: error: systemd-unit: the watchdog is 0 (none) or a number of seconds, not -1.0",
    ]
