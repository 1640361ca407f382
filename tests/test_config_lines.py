"""A typo in any table of a poll config is one line: what is wrong, what was meant, file:line.

Each case is a real file given to ``plcstack poll``: exit 2, one line on stderr, the name that
was probably meant, and the line of the offending key (or of its table's header when the error
is about the table as a whole). Before, ``[opcua]`` listed its known keys instead of a guess,
and north-side tables and unknown top-level tables had no line at all.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from plcstack.cli import main
from plcstack.errors import ConfigError
from plcstack.north.opcua_config import load_opcua_config

PLC = """[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:9"
tags = { strokes = "D100" }
"""


@pytest.mark.parametrize(
    ("tables", "line", "fragment"),
    [
        ('[poll]\ninterval = 1.0\n\n[mqt]\nurl = "mqtt://h"\n', 4,
         "unknown top-level key(s) mqt (did you mean mqtt?)"),
        ('[opcua]\nendpiont = "opc.tcp://127.0.0.1:4840"\n', 2,
         "[opcua]: unknown key(s) endpiont (did you mean endpoint?)"),
        ('[opcua]\nanonymous = "read"\n\n[opcua.users.bob]\nwrite = true\npassword = "x"\n', 6,
         "[opcua.users.bob]: unknown key(s) password (did you mean password_hash?); store a hash"),
        ('[metrics]\nport = 9108\n\n[influx]\nmeasurment = "m"\n', 5,
         "[influx]: unknown key(s) measurment (did you mean measurement?)"),
        ('[mqtt]\nurl = "mqtt://h"\nqso = 1\n', 3,
         "[mqtt]: unknown key(s) qso (did you mean qos?)"),
        ("[metrics]\nprot = 9108\n", 2, "[metrics]: unknown key(s) prot (did you mean port?)"),
        ('[audit]\npaht = "w.jsonl"\n', 2, "[audit]: unknown key(s) paht (did you mean path?)"),
        ("[modbus]\nunitid = 1\n", 2, "[modbus]: unknown key(s) unitid (did you mean unit_id?)"),
        ("[web]\nprot = 8080\n", 2, "[web]: unknown key(s) prot (did you mean port?)"),
        ("[report]\nmax_silence = 60\n[[report.rule]]\ntag = \"t*\"\ndeadbnd = 1\n", 5,
         "[[report.rule]] #1: unknown key(s) deadbnd (did you mean deadband?)"),
        # a mistake in a value: the key's line
        ('\n[mqtt]\nurl = "mqtt://h"\nqos = 5\n', 4, "[mqtt] qos must be 0..2, not 5"),
        # a mistake about the table as a whole: its header
        ('\n[audit]\nmax_bytes = 5000\n', 2, '[audit] needs path = "FILE"'),
        # an inline table: the line that opens it
        ('# the OPC UA side\nopcua = { endpiont = "x" }\n', 2, "endpiont (did you mean endpoint?)"),
    ],
)  # fmt: skip
def test_a_typo_in_any_table_is_one_line_with_the_guess_and_its_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], tables: str, line: int, fragment: str
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(tables + "\n" + PLC)
    code = main(["poll", str(path), "--format", "none", "--duration", "0.1"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("plcstack: error: "), err
    assert fragment in err, err
    assert err.rstrip().endswith(f"({path}:{line})"), err


def test_the_python_loader_of_opcua_points_at_the_line_too(tmp_path: Path) -> None:
    """``load_opcua_config`` (the Python API's way to the ``[opcua]`` table) reads the file
    itself: its errors name the file and line as ``plcstack poll`` does."""
    path = tmp_path / "plant.toml"
    path.write_text(PLC + '\n[opcua]\nanonymous = "read"\nendpiont = "opc.tcp://h:1"\n')
    with pytest.raises(ConfigError) as err:
        load_opcua_config(path)
    assert str(err.value) == (
        f"[opcua]: unknown key(s) endpiont (did you mean endpoint?) ({path}:8)"
    )
