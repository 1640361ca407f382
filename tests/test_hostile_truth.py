"""Issue 11, items 2, 3 and 5: errors that tell the truth about writes, backoff that cannot
overflow and also spaces fresh connections that never answer validly, and input limits.

Every test names the error type and the wording it promises; each was measured against the code
before the change (see the closing note of issue 11) and fails there.
"""

from __future__ import annotations

import asyncio
import pathlib
from typing import Any

import pytest

from plcstack.cli import main as cli_main
from plcstack.clients import connect
from plcstack.clients.base import MAY_OR_MAY_NOT
from plcstack.codecs.as511 import (
    ACK,
    DLE,
    STX,
    Delivery,
    PGConnection,
    write_job,
)
from plcstack.config import parse_config
from plcstack.durations import check_seconds
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    RemoteProtocolError,
)
from plcstack.poll.config import MIN_INTERVAL, ConfigError, PollConfig
from plcstack.sim import e71 as e71_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.sim.s5memory import Area
from plcstack.transports.backoff import Backoff
from tests.aio_helpers import ends_quietly
from tests.robust_helpers import MisbehavingProxy


# -- item 3: backoff ----------------------------------------------------------------------------
def test_backoff_never_overflows_and_stays_at_its_cap() -> None:
    """Before: the 1025th failure raised OverflowError (``2.0**1024``), about 8.5 h of a dead
    PLC at the 30 s cap, and every later read with it."""
    b = Backoff(jitter=0.0)
    delays = [b.next_delay() for _ in range(5000)]
    assert delays[:3] == [0.2, 0.4, 0.8]
    assert delays[-1] == 30.0 and b.failures == 5000
    huge = Backoff(initial=1.0, maximum=10.0, factor=1e300, jitter=0.0)
    assert [huge.next_delay() for _ in range(3)] == [1.0, 10.0, 10.0]


def test_backoff_refuses_infinite_parameters() -> None:
    with pytest.raises(ValueError, match="finite"):
        Backoff(maximum=float("inf"))


class _Garbler:
    """Accepts every connection and answers every request with bytes of no protocol."""

    def __init__(self) -> None:
        self.connections = 0
        self.port = 0
        self.server: asyncio.Server | None = None

    async def __aenter__(self) -> _Garbler:
        self.server = await asyncio.start_server(ends_quietly(self._handle), "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.server is not None
        self.server.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        try:
            while await reader.read(4096):
                writer.write(b"\x83\x25garbage")
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.transport.abort()


async def test_a_peer_that_garbles_every_answer_is_not_reconnected_every_request() -> None:
    """Before: a new connection per request, for ever (no backoff: TCP got in each time)."""
    async with _Garbler() as peer:
        async with connect(f"e71+tcp://127.0.0.1:{peer.port}?timeout=1") as plc:
            for _ in range(2):  # once is a glitch: the next request reconnects at once
                with pytest.raises(RemoteProtocolError):
                    await plc.read("D0")
            for _ in range(20):  # then reconnects wait for the backoff
                with pytest.raises(ConnectFailed) as info:
                    await plc.read("D0")
        assert peer.connections == 2
        text = str(info.value)
        assert "no valid answer on the last connection" in text
        assert "next reconnect attempt in" in text


# -- item 2: the truth about writes -------------------------------------------------------------
async def test_s5lan_write_executed_then_reset_is_connection_lost_may_or_may_not() -> None:
    """The module executes the write and the connection dies before the answer, on the first
    request of the connection. Before: ``ConnectFailed`` ("never got in") blaming "another
    client"; a caller trusting the type retries and writes twice."""
    async with await s5lan_sim.start() as sim:
        proxy = await MisbehavingProxy(sim.host, sim.port).start()
        try:
            proxy.script.mode = "close"
            url = f"s5lan://127.0.0.1:{proxy.port}?timeout=1"
            async with connect(url) as plc:
                with pytest.raises(PlcError) as info:
                    await plc.write("MB7", [0x5A])
            assert sim.memory.read_area(Area.FLAGS, 7, 1) == b"\x5a"  # it was executed
            assert type(info.value) is ConnectionLost
            text = str(info.value)
            assert MAY_OR_MAY_NOT in text
            assert "another client" not in text
        finally:
            await proxy.aclose()


async def test_e71_undocumented_end_code_is_a_protocol_error_not_a_refusal() -> None:
    """Before: random bytes ``83 25`` after an executed write became ``PlcErrorResponse``
    "PLC answered with error code 25H", saying nothing of the write having been executed."""
    async with await e71_sim.start() as sim:
        proxy = await MisbehavingProxy("127.0.0.1", sim.port).start()
        try:
            proxy.script.mode = "mutate"
            proxy.script.mutate = lambda _data: b"\x83\x25"
            async with connect(f"e71+tcp://127.0.0.1:{proxy.port}?timeout=1") as plc:
                with pytest.raises(PlcError) as info:
                    await plc.write("D5", [1234])
                assert not plc.transport.is_open  # closed, like any malformed answer
            assert sim.memory.read_words("D", 5, 1) == [1234]
            assert type(info.value) is RemoteProtocolError
            assert "end code 25H" in str(info.value) and MAY_OR_MAY_NOT in str(info.value)
            # a documented end code stays a PLC refusal
            proxy.script.mutate = lambda _data: b"\x83\x56"
            async with connect(f"e71+tcp://127.0.0.1:{proxy.port}?timeout=1") as plc:
                with pytest.raises(PlcErrorResponse, match="56H"):
                    await plc.write("D5", [1])
        finally:
            await proxy.aclose()


def test_as511_codec_reports_how_far_a_write_got() -> None:
    """The PG codec, not the client, knows whether the AG acknowledged a write's data."""
    pg = PGConnection(char_timeout=0.5, backoff=0.5)
    pg.submit(write_job(0x100, b"\x12\x34"), 0.0)
    assert pg.delivery is Delivery.NOT_SENT
    pg.receive_data(bytes([DLE, ACK, STX]), 0.01)  # ready, then STX after the function code
    pg.receive_data(bytes([0x16, DLE, 0x03]), 0.02)  # accept frame: the parameters go out
    pg.data_to_send()
    assert pg.delivery is Delivery.SENT
    pg.timer(5.0)  # the AG never acknowledges: the write may or may not have been executed
    assert pg.delivery is Delivery.SENT
    assert "may or may not" in pg.delivery.value
    pg2 = PGConnection(char_timeout=0.5, backoff=0.0)
    pg2.submit(write_job(0x100, b"\x12\x34"), 0.0)
    pg2.receive_data(bytes([DLE, ACK, STX, 0x16, DLE, 0x03]), 0.01)
    pg2.receive_data(bytes([DLE, ACK]), 0.02)  # step 9: the AG executed the write
    assert pg2.delivery is Delivery.ACKNOWLEDGED
    pg2.timer(5.0)  # the terminate phase is lost: the write was still executed
    assert pg2.delivery is Delivery.ACKNOWLEDGED


# -- item 5: input limits -----------------------------------------------------------------------
@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "0", "-1"])
def test_url_timeouts_must_be_finite_and_positive(value: str) -> None:
    """Before: ``?timeout=inf`` passed and crashed the E71 client with OverflowError."""
    with pytest.raises(AddressError) as info:
        connect(f"e71+tcp://127.0.0.1:5000?timeout={value}")
    assert "option timeout=" in str(info.value)


@pytest.mark.parametrize("value", [float("inf"), float("nan"), 0, -2.0, True, "2", None])
@pytest.mark.parametrize("name", ["timeout", "connect_timeout"])
def test_keyword_timeouts_are_checked_and_named(name: str, value: Any) -> None:
    with pytest.raises(AddressError) as info:
        options: dict[str, Any] = {name: value}
        connect("e71+tcp://127.0.0.1:5000", **options)
    assert isinstance(info.value, PlcError)
    assert f"option {name}=" in str(info.value)


@pytest.mark.parametrize("name", ["char_timeout", "response_timeout"])
def test_as511_keyword_durations_are_checked(name: str) -> None:
    with pytest.raises(AddressError, match=f"option {name}="):
        options: dict[str, Any] = {name: float("inf")}
        connect("as511+tcp://127.0.0.1:5000", **options)


def test_fetchwrite_life_ack_must_be_finite() -> None:
    with pytest.raises(AddressError, match="option life_ack="):
        connect("fetchwrite://127.0.0.1:5000?mk=1&life_ack=inf")


def test_check_seconds_accepts_finite_positive_numbers() -> None:
    assert check_seconds("t", 2) == 2.0
    assert check_seconds("t", 1e-9) == 1e-9
    with pytest.raises(AddressError):
        check_seconds("t", 10**400)


def test_cli_timeout_inf_is_bad_usage(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["read", "e71+tcp://127.0.0.1:9", "D0", "--timeout", "inf"]) == 2
    assert "option timeout=inf" in capsys.readouterr().err


def _config(interval: str) -> str:
    return (
        f'[poll]\ninterval = {interval}\n[[plc]]\nname = "a"\nurl = "e71+tcp://h:1"\n'
        '[plc.tags]\nx = "D0"\n'
    )


def test_scan_interval_has_a_documented_lower_bound() -> None:
    """Before: 1e-300 was accepted (a dead PLC then yielded 15k bad samples/s)."""
    with pytest.raises(ConfigError, match="at least 0.001 s"):
        parse_config(_config("1e-300"))
    assert parse_config(_config(str(MIN_INTERVAL))).poll.groups["default"] == MIN_INTERVAL
    with pytest.raises(ConfigError, match="at least 0.001"):
        PollConfig(plcs=(), groups={"default": 1e-6})


@pytest.mark.parametrize("depth", [40, 500, 5000])
def test_deeply_nested_toml_is_a_config_error(depth: int) -> None:
    """Before: 500 levels escaped as RecursionError (a traceback and exit 1)."""
    with pytest.raises(ConfigError, match="nested"):
        parse_config("a = " + "[" * depth + "]" * depth)


def test_cli_poll_with_deep_toml_exits_2(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "deep.toml"
    path.write_text("a = " + "[" * 500 + "]" * 500)
    assert cli_main(["poll", str(path), "--duration", "0.1"]) == 2
    assert "nested" in capsys.readouterr().err
