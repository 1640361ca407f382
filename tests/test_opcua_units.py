"""The OPC UA server's pieces that need no running server: status mapping, data types, the
``[opcua]`` configuration and password hashes, and the ``serve opcua`` command's usage errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("asyncua")  # the optional extra; CI installs it with [test]

from asyncua import ua

from plcstack import values as vt
from plcstack.config import parse_config
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    LocalProtocolError,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
    ValueDecodeError,
)
from plcstack.north.opcua import (
    STATUS_MAP,
    read_status,
    same_value,
    unit_id,
    variant_type,
    write_status,
)
from plcstack.north.opcua_config import (
    DEFAULT_ENDPOINT,
    OpcUaConfig,
    UserConfig,
    check_password,
    hash_password,
    load_opcua_config,
    parse_opcua_config,
)
from plcstack.poll.config import ConfigError, TagConfig

ROOT = Path(__file__).resolve().parent.parent
S = ua.StatusCodes
#: a valid stored hash (one PBKDF2 round: these tests check the format, not the strength)
HASH = hash_password("pw", iterations=1)
# -- status mapping and types ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("error", "status"),
    [
        (PlcTimeout, S.BadTimeout),
        (ConnectFailed, S.BadNoCommunication),
        (ConnectionLost, S.BadCommunicationError),
        (RemoteProtocolError, S.BadCommunicationError),
        (PlcErrorResponse, S.BadDeviceFailure),
        (ValueDecodeError, S.BadOutOfRange),
        (AddressError, S.BadConfigurationError),
        (LocalProtocolError, S.BadInternalError),
        (PlcError, S.BadUnexpectedError),
        (None, S.BadUnexpectedError),
    ],
)
def test_read_status_maps_each_error_type(error: type[PlcError] | None, status: int) -> None:
    assert read_status(error) == status


def test_write_status_of_a_value_that_does_not_fit_is_out_of_range() -> None:
    assert write_status(AddressError("value 70000 is outside ...")) == S.BadOutOfRange
    assert write_status(PlcTimeout("no answer")) == S.BadTimeout
    assert write_status(RuntimeError("bug")) == S.BadInternalError


def test_the_documented_status_table_is_the_one_in_the_code() -> None:
    text = (ROOT / "docs" / "opcua.md").read_text(encoding="utf-8")
    for kind, code, _ in STATUS_MAP:
        name = ua.StatusCode(code).name
        assert f"| `{kind.__name__}` | `{name}` |" in text, (kind.__name__, name)


#: every named value type -> its OPC UA type (16-bit points; raw depends on the point width)
EXPECTED_TYPES = {
    "raw": ua.VariantType.UInt16,
    "bool": ua.VariantType.Boolean,
    "int8": ua.VariantType.SByte,
    "uint8": ua.VariantType.Byte,
    "int16": ua.VariantType.Int16,
    "uint16": ua.VariantType.UInt16,
    "int32": ua.VariantType.Int32,
    "uint32": ua.VariantType.UInt32,
    "float32": ua.VariantType.Float,
    "bcd16": ua.VariantType.UInt16,
    "bcd32": ua.VariantType.UInt32,
    "kf": ua.VariantType.Int16,
    "kh": ua.VariantType.UInt16,
    "km": ua.VariantType.UInt16,
    "ky": ua.VariantType.String,
    "kc": ua.VariantType.String,
    "kt": ua.VariantType.Double,
    "kz": ua.VariantType.UInt16,
    "kg": ua.VariantType.Double,
}


def test_every_value_type_has_its_opc_ua_type() -> None:
    # a new value type must be given its OPC UA type here (and in docs/opcua.md) deliberately
    assert set(EXPECTED_TYPES) == set(vt.TYPES)
    for name, vtype in EXPECTED_TYPES.items():
        assert variant_type(TagConfig("t", "D0", vt.value_type(name)), 16) is vtype, name
    assert variant_type(TagConfig("t", "D0", vt.string(8)), 16) is ua.VariantType.String
    assert variant_type(TagConfig("t", "M0", vt.RAW), 1) is ua.VariantType.Boolean
    assert variant_type(TagConfig("t", "MB0", vt.RAW), 8) is ua.VariantType.Byte
    scaled = TagConfig("t", "D0", vt.INT16, scale=vt.Scale(0, 1, 0.0, 1.0))
    assert variant_type(scaled, 16) is ua.VariantType.Double


def test_a_nan_that_stays_is_no_change() -> None:
    nan = float("nan")
    assert same_value(nan, float("nan")) and same_value([1.0, nan], [1.0, float("nan")])
    assert not same_value(nan, 1.0) and not same_value([nan], [nan, nan])
    assert same_value(3, 3) and not same_value(3, 4) and not same_value(None, 0)


def test_unit_ids_are_unece_codes() -> None:
    assert unit_id("°C") == 0x43454C  # "CEL"
    assert unit_id("%") == 0x5031  # "P1"
    assert unit_id("furlong/fortnight") == -1


# -- configuration --------------------------------------------------------------------------------


def test_defaults_are_secure() -> None:
    config = OpcUaConfig()
    assert config.endpoint == DEFAULT_ENDPOINT and config.host == "127.0.0.1"
    assert config.port == 4840
    assert config.anonymous == "read"  # anonymous sessions may not write
    assert config.policies == ("NoSecurity",)  # nothing else works without a certificate
    assert config.users == ()


def test_a_certificate_turns_on_the_encrypting_policies_only(tmp_path: Path) -> None:
    config = parse_opcua_config(
        {"certificate": "cert.der", "private_key": "key.pem"}, base=tmp_path
    )
    assert config.certificate == tmp_path / "cert.der"
    assert config.policies and all(p.endswith("SignAndEncrypt") for p in config.policies)


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"endpoint": "http://127.0.0.1:4840"}, "opc.tcp://HOST:PORT"),
        ({"endpoint": "opc.tcp://127.0.0.1:99999"}, "out of range"),
        ({"anonymous": "maybe"}, "anonymous must be one of none, read, write"),
        ({"security_policies": ["Basic256Sha256_SignAndEncrypt"]}, "need certificate"),
        ({"security_policies": ["Rot13"]}, "unknown policy 'Rot13'"),
        ({"security_policies": []}, "at least one policy"),
        ({"certificate": "c.der"}, "go together"),
        ({"anonymous": "none"}, "nobody could log in"),
        ({"users": {"bob": {"password": "x"}}}, "--hash-password"),
        ({"users": {"bob": {"password_hash": "plain"}}}, "pbkdf2_sha256$ITERATIONS$SALT$HASH"),
        ({"users": {"bob": {"password_hash": HASH, "write": "yes"}}}, "true or false"),
        ({"colour": "blue"}, "[opcua]: unknown key(s) colour"),
        ({"endpiont": "opc.tcp://h:1"}, "endpiont (did you mean endpoint?)"),
        ({"trusted_client_certificates": "t/"}, "needs a security policy but None"),
        (
            {
                "trusted_client_certificates": "t/",
                "certificate": "c.der",
                "private_key": "k.pem",
                "security_policies": ["None", "Basic256Sha256_SignAndEncrypt"],
            },
            "the trust list would not apply",
        ),
    ],
)
def test_bad_settings_are_refused_with_the_reason(section: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_opcua_config(section)
    assert message in str(err.value)


def test_passwords_are_not_sent_in_plain_text_beyond_loopback() -> None:
    users = (UserConfig("bob", HASH, True),)
    OpcUaConfig(endpoint="opc.tcp://localhost:4840", users=users)  # loopback: allowed
    with pytest.raises(ConfigError, match="plain text"):
        OpcUaConfig(endpoint="opc.tcp://0.0.0.0:4840", users=users)


def test_password_hashes_check_the_password_and_never_contain_it() -> None:
    stored = hash_password("s3cret", iterations=100)
    assert "s3cret" not in stored
    assert check_password("s3cret", stored)
    assert not check_password("s3cret ", stored)
    assert hash_password("s3cret", iterations=100) != stored  # salted


def test_the_poll_config_takes_writable_tags_and_an_opcua_table(tmp_path: Path) -> None:
    text = """
[opcua]
listen = "127.0.0.1:4841"
path = "/plant"
anonymous = "write"

[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:5000"
[plc.tags]
strokes = { address = "D100", type = "uint16", writable = true }
force = { address = "D102", unit = "kN" }
"""
    config = parse_config(text)
    tags = {t.name: t for t in config.plcs[0].tags}
    assert tags["strokes"].writable and not tags["force"].writable
    assert tags["force"].unit == "kN" and tags["strokes"].unit is None
    path = tmp_path / "plant.toml"
    path.write_text(text, encoding="utf-8")
    opcua = load_opcua_config(path)
    assert opcua.port == 4841 and opcua.anonymous == "write"
    with pytest.raises(ConfigError, match="unit must be a non-empty string"):
        parse_config(text.replace('unit = "kN"', "unit = 3"))
    with pytest.raises(ConfigError, match="writable must be true or false"):
        parse_config(text.replace("writable = true", 'writable = "yes"'))
    with pytest.raises(ConfigError, match=r"\[opcua\] must be a table"):
        parse_config("opcua = 3\n" + text.split("[opcua]", 1)[1].split("\n", 4)[4])


# -- the command line ---------------------------------------------------------------------------


def run_cli(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "plcstack", "serve", "opcua", *args],
        input=stdin,
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )


def test_hash_password_prints_a_hash_the_config_accepts() -> None:
    done = run_cli("--hash-password", stdin="op-secret\n")
    assert done.returncode == 0, done.stderr
    stored = done.stdout.strip()
    assert check_password("op-secret", stored)
    parse_opcua_config({"users": {"op": {"password_hash": stored, "write": True}}})


def test_a_bad_opcua_table_exits_with_the_usage_code(tmp_path: Path) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(
        '[opcua]\nanonymous = "maybe"\n[[plc]]\nurl = "e71+tcp://127.0.0.1:5000"\n'
        '[plc.tags]\nx = "D0"\n',
        encoding="utf-8",
    )
    done = run_cli(str(path))
    assert done.returncode == 2
    assert "anonymous must be one of" in done.stderr
