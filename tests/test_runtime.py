"""One runtime for every face: a configured face that cannot start is exit 2 with one line
naming it, and what was started before it is stopped again."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from plcstack.cli import main


def _plant(tmp_path: Path, table: str) -> str:
    path = tmp_path / "plant.toml"
    path.write_text(
        '[[plc]]\nname = "press1"\nurl = "e71+tcp://127.0.0.1:1"\n'
        '[plc.tags]\nstrokes = { address = "D100", modbus = "hr:0" }\n' + table
    )
    return str(path)


@pytest.mark.parametrize(
    ("table", "line"),
    [
        ('[modbus]\nendpoint = "127.0.0.1:{port}"\n', "modbus cannot start: Modbus server cannot"),
        ("[web]\nport = {port}\n", "[web] cannot serve the console on 127.0.0.1:{port}"),
        pytest.param(
            '[opcua]\nendpoint = "opc.tcp://127.0.0.1:{port}/plcstack"\n',
            "opcua cannot start: OPC UA server cannot listen on opc.tcp://127.0.0.1:{port}",
            marks=pytest.mark.slow,  # asyncua builds its server first: 3 s here
        ),
        ("[metrics]\nport = {port}\n", "[metrics] cannot serve /metrics on 127.0.0.1:{port}"),
    ],
    ids=["modbus", "web", "opcua", "metrics"],
)
def test_a_face_that_cannot_start_is_exit_2_with_one_line_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], table: str, line: str
) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = _plant(tmp_path, table.format(port=port))
        code = main(["poll", config, "--format", "none", "--duration", "5"])
    err = capsys.readouterr().err
    errors = [x for x in err.splitlines() if x.startswith("plcstack: error:")]
    assert code == 2, err
    assert len(errors) == 1, err
    assert line.format(port=port) in errors[0], errors
