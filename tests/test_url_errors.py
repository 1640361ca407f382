"""URLs and the error hierarchy: the first thing a user touches, so every mistake is named."""

import pytest

import plcstack
from plcstack.clients import SCHEMES, E71Client, FetchWriteClient
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    OptionError,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.url import URL_FORMS, parse_url


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


@pytest.mark.parametrize(
    ("url", "keywords", "option", "fragment"),
    [
        (
            "e71+tcp://h:1",
            {"tiemout": 3},
            "tiemout",
            "unknown option tiemout (keyword): did you mean timeout?",
        ),
        ("e71+tcp://h:1?tiemout=3", {}, "tiemout", "unknown option tiemout (URL query)"),
        ("s5lan://h:1?code=ascii", {}, "code", "does not apply to s5lan://"),
        ("e71+tcp://h:1", {"timeout": 0}, "timeout", "greater than 0"),
        ("e71+tcp://h:1?timeout=inf", {}, "timeout", "finite"),
        ("e71+tcp://h:1?timeout=x", {}, "timeout", "option timeout='x'"),
        ("e71+tcp://h:1?code=ebcdic", {}, "code", "not one of binary, ascii"),
        ("e71+tcp://h:1?pc=GG", {}, "pc", "option pc='GG'"),
        ("fetchwrite://h:1?mk=maybe", {}, "mk", "not a boolean"),
        ("fetchwrite://h:1", {"write_port": 70000}, "write_port", "outside 1..65535"),
        ("as511+tcp://h:1?parity=E", {}, "parity", "does not apply to as511+tcp://"),
        ("as511:///dev/ttyS9?stopbits=3", {}, "stopbits", "not 1, 1.5 or 2"),
        ("e71+tcp://h:1?backoff=1", {}, "backoff", "Python only"),
        ("e71+tcp://h:1", {"pc": None}, "pc", "not an integer"),
        ("fetchwrite://h:1", {"mk": None}, "mk", "not a boolean"),
    ],
)
def test_bad_options_are_option_errors_naming_the_option(
    url: str, keywords: dict[str, object], option: str, fragment: str
) -> None:
    with pytest.raises(OptionError) as info:
        plcstack.connect(url, **keywords)  # type: ignore[arg-type]
    assert info.value.option == option
    assert fragment in str(info.value)
    assert str(info.value).startswith(url)
    assert isinstance(info.value, AddressError | PlcError)


def test_url_and_keywords_share_one_schema() -> None:
    a = plcstack.connect("e71+tcp://h:1?code=ascii&pc=1F&timeout=1.5&monitoring_timer=3")
    b = plcstack.connect("e71+tcp://h:1", code="ascii", pc=0x1F, timeout=1.5, monitoring_timer=3)
    for plc in (a, b):
        assert isinstance(plc, E71Client)
        assert (plc.code.value, plc.pc, plc.timeout, plc.monitoring_timer) == ("ascii", 31, 1.5, 3)
    # a keyword wins over the query
    c = plcstack.connect("fetchwrite://h:1?mk=0&timeout=5", mk=True, timeout=1)
    assert isinstance(c, FetchWriteClient) and c.mk is True and c.timeout == 1.0
    assert plcstack.connect("s5lan://h:1?strict=off").strict is False  # type: ignore[attr-defined]


def test_scheme_table_holds_classes() -> None:
    assert SCHEMES["e71+udp"] is E71Client
    assert set(SCHEMES) == set(URL_FORMS)


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
