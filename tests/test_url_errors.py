"""URLs and the error hierarchy: the first thing a user touches, so every mistake is named."""

import pytest

import plcstack
from plcstack import url as url_mod
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.url import parse_url


@pytest.mark.parametrize(
    ("text", "scheme", "host", "port", "path", "transport"),
    [
        ("e71+tcp://10.0.0.5:5000", "e71+tcp", "10.0.0.5", 5000, None, "tcp"),
        ("E71+UDP://plc1:5001?code=ascii", "e71+udp", "plc1", 5001, None, "udp"),
        ("s5lan://127.0.0.1:5010", "s5lan", "127.0.0.1", 5010, None, "tcp"),
        ("fetchwrite://h:2000?mk=1", "fetchwrite", "h", 2000, None, "tcp"),
        ("as511:///dev/ttyS0?baud=9600", "as511", None, None, "/dev/ttyS0", "serial"),
        ("as511+tcp://[::1]:5020", "as511+tcp", "::1", 5020, None, "tcp"),
    ],
)
def test_every_scheme_parses(
    text: str, scheme: str, host: str | None, port: int | None, path: str | None, transport: str
) -> None:
    parsed = parse_url(text)
    assert (parsed.scheme, parsed.host, parsed.port, parsed.path) == (scheme, host, port, path)
    assert parsed.transport == transport
    assert parsed.raw == text


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("10.0.0.5:5000", "not a PLC URL"),
        ("modbus://h:502", "unknown scheme 'modbus'"),
        ("e71+tcp://h", "missing port"),
        ("e71+tcp://:5000", "missing host"),
        ("e71+tcp://h:99999", "port is not a number"),
        ("s5lan://h:5010/x", "unexpected path"),
        ("as511://host/dev/ttyS0", "three slashes"),
        ("as511://", "missing device path"),
        ("e71+tcp://h:1?code=ascii&code=binary", "given twice"),
        ("e71+tcp://[::1:5000", "malformed URL"),  # urlsplit's ValueError, not a crash
    ],
)
def test_bad_urls_are_named(text: str, fragment: str) -> None:
    with pytest.raises(AddressError) as info:
        parse_url(text)
    assert fragment in str(info.value)
    assert str(info.value).startswith(text)


def test_typed_options() -> None:
    parsed = parse_url("e71+tcp://h:1?timeout=1.5&mk=yes&n=0x10&code=ascii")
    assert parsed.get_float("timeout", 2.0) == 1.5
    assert parsed.get_bool("mk", False) is True
    assert parsed.get_int("n", 0, 0, 255) == 16
    assert parsed.get_str("code", "binary", ("binary", "ascii")) == "ascii"
    assert parsed.get_int("absent", 7) == 7
    with pytest.raises(AddressError, match="outside 0..10"):
        parsed.get_int("n", 0, 0, 10)
    with pytest.raises(AddressError, match="not one of"):
        parsed.get_str("code", "binary", ("binary",))
    with pytest.raises(AddressError, match="not a boolean"):
        parse_url("e71+tcp://h:1?mk=maybe").get_bool("mk", False)
    with pytest.raises(AddressError, match="greater than 0"):
        parse_url("e71+tcp://h:1?timeout=0").get_float("timeout", 2.0)
    with pytest.raises(AddressError, match="unknown option"):
        parsed.check_options({"timeout", "code"})


def test_scheme_whose_module_is_missing_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(
        url_mod.SCHEMES, "e71+tcp", ("plcstack.clients.not_built_yet:Nope", True, False)
    )
    with pytest.raises(AddressError, match="'e71\\+tcp' is not built"):
        plcstack.connect("e71+tcp://h:1")


def test_error_messages_name_plc_request_and_meaning() -> None:
    err = PlcErrorResponse(0x55, "write during RUN not allowed", code_text="55H")
    err.bind(plc="e71+tcp://h:1", request="write D100 x1")
    err.bind(plc="other", request="other")  # first binding wins
    assert str(err) == (
        "e71+tcp://h:1: write D100 x1: PLC answered with error code 55H: "
        "write during RUN not allowed"
    )
    assert (err.code, err.meaning) == (0x55, "write during RUN not allowed")
    assert isinstance(PlcTimeout("x"), TimeoutError)
    assert isinstance(ConnectFailed("x"), ConnectionLost)
    assert isinstance(ConnectionLost("x"), ConnectionError)
    assert isinstance(AddressError("x"), ValueError)
    assert str(PlcError("only a message")) == "only a message"
