"""One configuration model: every table read by one set of checks, one spelling of a listening
address, the same rules for every command, the command line applied in one place.

Before, a listener was written four ways (``host`` + ``port``, ``endpoint = "H:P"``, an
``opc.tcp://`` URL), each table checked its ports its own way, ``--web-port`` and
``--metrics-port`` were applied differently by each command, and three functions called
``load_config`` meant three things.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from plcstack.checks import Listen, Table, parse_seconds, parse_size
from plcstack.cli import main
from plcstack.config import Config, load_config, parse_config
from plcstack.config.overrides import Overrides, apply_overrides
from plcstack.errors import ConfigError
from plcstack.north.metrics import MetricsSettings
from plcstack.north.modbus.config import ModbusSettings
from plcstack.north.web.settings import WebSettings

PLC = """
[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:9"
tags = { strokes = { address = "D100", modbus = "hr:0" } }
"""


def _listening(config: Config, table: str) -> str:
    north = config.north
    if table == "opcua":
        assert north.opcua is not None
        return north.opcua.endpoint
    settings = {"metrics": north.metrics, "web": north.web, "modbus": north.modbus}[table]
    assert isinstance(settings, MetricsSettings | WebSettings | ModbusSettings)
    return str(settings.listen)


#: (table, the new spelling, an old one, what both mean, the new spelling the warning names)
SPELLINGS = [
    ("metrics", 'listen = "0.0.0.0:9200"', 'host = "0.0.0.0"\nport = 9200', "0.0.0.0:9200",
     'listen = "0.0.0.0:9200"'),
    ("metrics", 'listen = "127.0.0.1:9200"', "port = 9200", "127.0.0.1:9200",
     'listen = "127.0.0.1:9200"'),
    ("web", 'listen = "[::1]:8081"', 'host = "::1"\nport = 8081', "[::1]:8081",
     'listen = "[::1]:8081"'),
    ("modbus", 'listen = "0.0.0.0:502"', 'endpoint = "0.0.0.0:502"', "0.0.0.0:502",
     'listen = "0.0.0.0:502"'),
    ("opcua", 'listen = "0.0.0.0:4841"', 'endpoint = "opc.tcp://0.0.0.0:4841/plcstack"',
     "opc.tcp://0.0.0.0:4841/plcstack", 'listen = "0.0.0.0:4841" instead'),
    ("opcua", 'listen = "10.0.0.9:4840"\npath = "/ua"', 'endpoint = "opc.tcp://10.0.0.9/ua"',
     "opc.tcp://10.0.0.9:4840/ua", 'listen = "10.0.0.9:4840" and path = "/ua"'),
]  # fmt: skip


@pytest.mark.parametrize(("table", "new", "old", "means", "named"), SPELLINGS)
def test_every_listener_is_listen_host_port_and_the_old_spelling_loads_with_one_warning(
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    table: str,
    new: str,
    old: str,
    means: str,
    named: str,
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(f"[{table}]\n{new}\n{PLC}")
    with caplog.at_level(logging.WARNING, logger="plcstack"):
        config = load_config(path)
    assert _listening(config, table) == means
    assert not caplog.records and not config.notices
    path.write_text(f"# the plant\n[{table}]\n{old}\n{PLC}")
    with caplog.at_level(logging.WARNING, logger="plcstack"):
        again = load_config(path)
    assert _listening(again, table) == means
    assert again == config  # the same configuration, whichever way it was written
    (record,) = caplog.records
    assert record.levelno == logging.WARNING and record.name == "plcstack.config"
    text = record.getMessage()
    assert f"[{table}]" in text and "deprecated" in text and named in text, text
    assert text.endswith(f"({path}:3)"), text
    assert again.notices == (text,)


@pytest.mark.parametrize(
    ("table", "both"),
    [
        ("web", 'listen = "127.0.0.1:1"\nport = 2'),
        ("metrics", 'listen = "127.0.0.1:1"\nhost = "0.0.0.0"'),
        ("modbus", 'listen = "127.0.0.1:1"\nendpoint = "127.0.0.1:2"'),
        ("opcua", 'listen = "127.0.0.1:1"\nendpoint = "opc.tcp://127.0.0.1:2/x"'),
    ],
)
def test_both_spellings_at_once_are_refused(tmp_path: Path, table: str, both: str) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(f"[{table}]\n{both}\n{PLC}")
    with pytest.raises(ConfigError, match="both say where to listen") as caught:
        load_config(path)
    assert str(caught.value).endswith(f"({path}:3)")


@pytest.mark.parametrize(
    ("text", "host", "port"),
    [
        ("127.0.0.1:8080", "127.0.0.1", 8080),
        ("0.0.0.0:0", "0.0.0.0", 0),
        ("[::1]:4840", "::1", 4840),
        ("[fe80::1%eth0]:502", "fe80::1%eth0", 502),
        ("plant-gw.local:65535", "plant-gw.local", 65535),
    ],
)
def test_listen_addresses(text: str, host: str, port: int) -> None:
    assert Listen.parse(text) == Listen(host, port)
    assert str(Listen(host, port)) == text


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("localhost", "the port is missing"),
        ("::1:80", "IPv6 address in brackets"),
        ("h:70000", "port 0..65535"),
        ("h:-1", "port 0..65535"),
        (":80", '"HOST:PORT"'),
        ("h:\uff18\uff10", "port 0..65535"),  # full-width digits: str.isdigit says yes
        ("a b:80", '"HOST:PORT"'),
        (8080, "not 8080"),
    ],
)
def test_bad_listen_addresses_say_the_form(text: object, fragment: str) -> None:
    with pytest.raises(ValueError, match="HOST:PORT") as caught:
        Listen.parse(text)
    assert fragment in str(caught.value)
    assert Listen.parse("8080", default_host="127.0.0.1") == Listen("127.0.0.1", 8080)


@given(
    st.one_of(
        st.ip_addresses().map(str),
        st.from_regex(r"[a-z][a-z0-9\-]{0,20}(\.[a-z0-9]{1,8}){0,3}", fullmatch=True),
    ),
    st.integers(0, 65535),
)
def test_a_listen_address_prints_as_it_parses(host: str, port: int) -> None:
    listen = Listen(host, port)
    assert Listen.parse(str(listen)) == listen


@pytest.mark.parametrize(
    ("value", "size"),
    [(4096, 4096), ("4 MiB", 4 << 20), ("500 kB", 500_000), ("1.5GiB", 3 << 29), ("7 B", 7)],
)
def test_sizes_take_a_unit(value: object, size: int) -> None:
    assert parse_size(value) == size


@pytest.mark.parametrize("value", ["4 MB/s", "x", "-1", "1.3 B", True, 1.5, None, "4 mib ram"])
def test_sizes_without_sense_are_refused(value: object) -> None:
    with pytest.raises(ValueError, match="number of bytes"):
        parse_size(value)


@pytest.mark.parametrize(
    ("value", "seconds"),
    [(2.5, 2.5), (3, 3.0), ("500ms", 0.5), ("30s", 30.0), ("15 m", 900.0), ("1min", 60.0),
     ("12h", 43200.0), ("7d", 604800.0), ("2w", 1209600.0)],
)  # fmt: skip
def test_durations_take_a_unit(value: object, seconds: float) -> None:
    assert parse_seconds(value) == seconds


@pytest.mark.parametrize(
    "value", [0, -1, "30", "7 days", float("inf"), float("nan"), True, 10**400]
)
def test_durations_without_sense_are_refused(value: object) -> None:
    with pytest.raises(ValueError, match="number of seconds"):
        parse_seconds(value)
    assert parse_seconds(0, zero=True) == 0.0


def test_a_size_in_a_table_takes_a_unit_and_its_bounds(tmp_path: Path) -> None:
    config = parse_config(
        '[mqtt]\nbuffer_memory = "1 MiB"\nbuffer_max = "2 GiB"\n[audit]\npath = "a.jsonl"\n'
        'max_bytes = "64 KiB"\n' + PLC
    )
    assert config.north.mqtt is not None and config.north.audit is not None
    assert config.north.mqtt.buffer_memory == 1 << 20
    assert config.north.mqtt.buffer_max == 2 << 30
    assert config.north.audit.max_bytes == 64 << 10
    with pytest.raises(ConfigError, match=r"max_bytes must be 4 KiB to 1 TiB, not '1 kB'"):
        parse_config('[audit]\npath = "a"\nmax_bytes = "1 kB"\n' + PLC)


def test_relative_paths_are_taken_from_the_file(tmp_path: Path) -> None:
    (tmp_path / "etc").mkdir()
    path = tmp_path / "etc" / "plant.toml"
    path.write_text(
        '[mqtt]\nbuffer_path = "q/mqtt.sqlite"\n[audit]\npath = "/var/log/a.jsonl"\n'
        '[opcua]\ncertificate = "c.der"\nprivate_key = "k.pem"\n' + PLC
    )
    north = load_config(path).north
    assert north.mqtt is not None and north.audit is not None and north.opcua is not None
    assert north.mqtt.buffer_path == str(tmp_path / "etc" / "q" / "mqtt.sqlite")
    assert north.audit.path == "/var/log/a.jsonl"
    assert north.opcua.certificate == tmp_path / "etc" / "c.der"


#: a mistake in a value of each table, and the text that names it; the line is the key's
VALUES = [
    ("metrics", 'listen = "127.0.0.1:99999"', "[metrics] listen must be"),
    ("web", "trend_seconds = 5", "[web] trend_seconds must be 10..3600, not 5"),
    ("web", 'write_token_env = "A=B"', "[web] write_token_env must name an environment"),
    ("modbus", "unit_id = 300", "[modbus] unit_id must be 0..255, not 300"),
    ("modbus", "idle_timeout = -1", "[modbus] idle_timeout must be a number of seconds"),
    ("mqtt", "qos = 5", "[mqtt] qos must be 0..2, not 5"),
    ("mqtt", 'mode = "plain"', '[mqtt] mode must be "json" or "sparkplug", not \'plain\''),
    ("mqtt", "timeout = 0.1", "[mqtt] timeout must be from 0.5 seconds to 5 minutes, not 0.1"),
    ("history", 'retention = "5m"', "[history] retention must be at least 10 minutes, not '5m'"),
    ("mqtt", 'buffer_max = "lots"', "[mqtt] buffer_max must be a number of bytes"),
    ("influx", 'layout = "wide"', '[influx] layout must be "fields" or "typed"'),
    ("influx", 'url = "http://h:99999"', "[influx] url has a bad port: 'http://h:99999'"),
    (
        "influx",
        'url = "http://h:8086"\ndatabase = "p"\nbatch_wait = "2h"',
        "[influx] batch_wait must be at most 1 minute, not '2h'",
    ),
    (
        "influx",
        'url = "http://h:8086"\ndatabase = "p"\nbuffer_max = "lots"',
        "[influx] buffer_max must be a number of bytes",
    ),
    ("influx", 'database = "p"', '[influx] database needs url = "http://HOST:PORT"'),
    ("mqtt", 'url = "mqtt://u:pw@h"', "[mqtt] url must not carry credentials"),
    ("opcua", "max_clients = 0", "opcua.max_clients must be 1..10000"),
    (
        "opcua",
        "max_clients_per_host = 4",
        "[opcua] max_clients_per_host is not taken here: the"
        " OPC UA library (asyncua) admits connections without telling hosts apart",
    ),
    (
        "opcua",
        'idle_timeout = "5m"',
        "[opcua] idle_timeout is not taken here: the OPC UA"
        " library (asyncua) ends an idle session by its session timeout",
    ),
    ("opcua", 'path = "plcstack"', '[opcua] path must be a URL path such as "/plcstack"'),
    ("audit", 'path = "a"\nbackups = -1', "[audit] backups must be 0..1000, not -1"),
]


@pytest.mark.parametrize(("table", "line", "message"), VALUES)
def test_a_bad_value_in_any_table_points_at_its_key(
    tmp_path: Path, table: str, line: str, message: str
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(f"# plant\n\n[{table}]\n{line}\n{PLC}")
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    text = str(caught.value)
    assert message in text, text
    assert text.endswith(f"({path}:{3 + line.count(chr(10)) + 1})"), text


COMMANDS = [
    ["poll", "{path}", "--format", "none", "--duration", "0.1"],
    ["serve", "opcua", "{path}", "--duration", "0.1"],
    ["serve", "modbus", "{path}", "--duration", "0.1"],
    ["tags", "list", "{path}"],
]


@pytest.mark.parametrize("argv", COMMANDS, ids=["poll", "serve-opcua", "serve-modbus", "tags-list"])
@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        (f"[modbus]\nunit_id = 300\n{PLC}", "[modbus] unit_id must be 0..255, not 300"),
        (f"[web]\nprot = 1\n{PLC}", "[web]: unknown key(s) prot (did you mean port?)"),
        (f"[[plc]]\nname = 3\n{PLC}", "PLC name must be a non-empty string"),
    ],
)
def test_every_command_reads_the_file_by_the_same_rules(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    argv: list[str],
    text: str,
    fragment: str,
) -> None:
    """The same file is refused with the same line by every command that reads it (before,
    ``serve opcua`` checked names and tables that ``poll`` did not, and the other way round)."""
    path = tmp_path / "plant.toml"
    path.write_text(text)
    code = main([a.format(path=path) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and fragment in err and f"({path}:" in err, err


def test_a_file_read_twice_is_the_same_configuration(tmp_path: Path) -> None:
    """Every table compares by value (a reload tells a changed table from an unchanged one):
    report rules too, which were a closure before."""
    text = (
        '[mqtt]\nurl = "mqtt://127.0.0.1:1883"\n[report]\nmax_silence = 60\n'
        '[[report.rule]]\nplc = "press*"\ndeadband = 0.5\n[web]\n[metrics]\n[modbus]\n'
        '[opcua]\n[audit]\npath = "a.jsonl"\n[influx]\nlayout = "typed"\n' + PLC
    )
    assert parse_config(text) == parse_config(text)
    changed = text.replace("deadband = 0.5", "deadband = 0.6")
    assert parse_config(changed).north.report != parse_config(text).north.report
    assert parse_config(changed).north.mqtt == parse_config(text).north.mqtt


def test_the_command_line_is_applied_in_one_place() -> None:
    config = parse_config('[metrics]\nlisten = "0.0.0.0:9108"\n' + PLC)
    assert apply_overrides(config, Overrides()) is config
    both = apply_overrides(config, Overrides(web_port=0, metrics_port=9200))
    assert both.north.metrics == MetricsSettings("0.0.0.0", 9200)  # the host stays the file's
    assert both.north.web == WebSettings(port=0)  # a console with its defaults
    assert both.poll is config.poll
    for bad in (-1, 65536, True):
        with pytest.raises(ConfigError, match="must be 0..65535"):
            Overrides(metrics_port=bad)


def test_a_table_read_without_a_file_says_its_notice_at_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The Python API (a table read without a loader) still hears about an old spelling."""
    from plcstack.north.web.settings import parse_web

    with caplog.at_level(logging.WARNING, logger="plcstack.config"):
        assert parse_web({"port": 1}) == WebSettings(port=1)
    assert "[web] port is deprecated" in caplog.text
    with pytest.raises(ConfigError, match=r"\[x\] must be a table"):
        Table.of(3, "x")
