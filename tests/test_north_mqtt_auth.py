"""MQTT client certificates and logins against a real mosquitto: accepted, and refused with a
typed error that names the broker and says what to change; credentials read at connect time."""

from __future__ import annotations

import asyncio
import logging
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from plcstack.cli import main
from plcstack.config import load_config
from plcstack.errors import ConnectFailed
from plcstack.north.mqtt import MqttSink, parse_mqtt
from plcstack.poll.config import ConfigError
from tests.aio_helpers import eventually
from tests.north_certs import Authority
from tests.north_helpers import sample, subscriber
from tests.scan_helpers import scan as as_scan
from tests.servers import Mosquitto, ServerUnavailable, free_port


def started(broker: Mosquitto) -> Mosquitto:
    try:
        broker.start()
    except ServerUnavailable as exc:
        broker.close()
        pytest.fail(str(exc), pytrace=False)
    return broker


class TlsBroker:
    """mosquitto with its plain listener (for the test's subscriber) and a TLS listener that
    requires a client certificate signed by ``authority``."""

    def __init__(self, directory: Path) -> None:
        self.authority = Authority.create(directory)
        server_cert, server_key = self.authority.issue(directory, "127.0.0.1", server=True)
        self.client_cert, self.client_key = self.authority.issue(directory, "line1", server=False)
        self.tls_port = free_port()
        self.broker = started(
            Mosquitto(
                extra_config=f"listener {self.tls_port} 127.0.0.1\n"
                f"cafile {self.authority.ca}\ncertfile {server_cert}\nkeyfile {server_key}\n"
                "require_certificate true\n"
            )
        )
        self.url = f"mqtts://127.0.0.1:{self.tls_port}"

    def settings(self, **table: Any) -> Any:
        return parse_mqtt(
            {"url": self.url, "ca_file": str(self.authority.ca), "reconnect_max": 0.2, **table}
        )


@pytest.fixture
def tls_broker(tmp_path: Path) -> Iterator[TlsBroker]:
    broker = TlsBroker(tmp_path)
    try:
        yield broker
    finally:
        broker.broker.close()


async def first_failure(sink: MqttSink, timeout: float = 10) -> None:
    async with asyncio.timeout(timeout):
        while sink.last_error is None:  # noqa: ASYNC110 - polls the sink's state
            await asyncio.sleep(0.02)


async def refused(sink: MqttSink, match: str) -> ConnectFailed:
    """Start ``sink``, wait for its first failed connect and return the ``ConnectFailed`` that
    waiting for a connection then raises (its message must match ``match``); the sink is
    closed after."""
    await sink.start()
    try:
        await first_failure(sink)
        with pytest.raises(ConnectFailed, match=match) as raised:
            await sink.wait_connected(0.01)
    finally:
        await sink.aclose(drain=0)
    return raised.value


async def test_a_client_certificate_signed_by_the_brokers_ca_gets_in(tls_broker: TlsBroker) -> None:
    host, port = tls_broker.broker.host, tls_broker.broker.port
    async with subscriber(host, port, "plcstack/#") as sub:
        sink = MqttSink(
            tls_broker.settings(
                cert_file=str(tls_broker.client_cert), key_file=str(tls_broker.client_key)
            )
        )
        await sink.start()
        await sink.wait_connected(10)
        sink.submit([as_scan(sample("p", "n", 1))])
        await sub.wait_for(lambda s: any("/data/" in t for t, _ in s.messages))
        await sink.aclose()
    assert sink.last_error is None


@pytest.mark.slow  # several seconds: run by the slow run
async def test_no_client_certificate_is_a_typed_error_naming_the_broker(
    tls_broker: TlsBroker, caplog: pytest.LogCaptureFixture
) -> None:
    # a limit a loaded machine's TLS handshake fits in (as for the foreign CA below)
    sink = MqttSink(tls_broker.settings(timeout=1.5))
    with caplog.at_level(logging.WARNING, logger="plcstack.north.mqtt"):
        await sink.start()
        try:
            await first_failure(sink)
            with pytest.raises(ConnectFailed) as raised:
                await sink.wait_connected(0.01)
            # the sink keeps trying (a broker's CA can be fixed without restarting us)...
            connects_before = sink.stats.connects
            await eventually(lambda: sink.stats.failures >= 2, "a second connection attempt")
        finally:
            await sink.aclose(drain=0)
    text = str(raised.value)
    assert text.startswith(f"MQTT broker {tls_broker.url}: connect: ")
    # the broker's alert, or only its close when the alert lost the race (TLS 1.3 checks the
    # client's certificate after the handshake; see mqtt_errors.py): either way the message
    # says to set the certificate
    upper = text.upper()
    if "EOF OCCURRED IN VIOLATION OF PROTOCOL" in upper:
        assert "if it requires a client certificate, set [mqtt] cert_file and key_file" in text
    else:
        assert "the broker requires a client certificate; set [mqtt] cert_file and key_file" in text
        assert "CERTIFICATE_REQUIRED" in upper or "DID NOT RETURN A CERTIFICATE" in upper
    assert sink.stats.connects == connects_before == 0
    assert sink.stats.failures >= 2
    # ...and says so once, not once per attempt
    warnings = [r for r in caplog.records if "client certificate" in r.getMessage()]
    assert len(warnings) == 1, [r.getMessage() for r in caplog.records]


async def test_a_client_certificate_of_another_ca_is_refused_with_the_reason(
    tls_broker: TlsBroker, tmp_path: Path
) -> None:
    impostor = Authority.create(tmp_path, "impostor CA")
    cert, key = impostor.issue(tmp_path, "line1-forged", server=False)
    # The rejection is known when the connect gives up (the alert is captured from paho's log
    # by then), so the limit must outlast a TLS handshake on a loaded machine: with 0.5 s the
    # handshake once had not finished, and the failure was a plain timeout.
    sink = MqttSink(tls_broker.settings(timeout=1.5, cert_file=str(cert), key_file=str(key)))
    error = await refused(sink, "rejected our client certificate")
    assert str(error).startswith(f"MQTT broker {tls_broker.url}: connect: ")
    # the broker's alert, or only its close when the alert lost the race (see mqtt_errors.py):
    # the message says the certificate was rejected either way
    text = str(error).upper()
    assert "UNKNOWN_CA" in text or "EOF OCCURRED IN VIOLATION OF PROTOCOL" in text, text


@pytest.mark.parametrize("cert_file", [None, "/etc/plc/line1.crt"])
def test_a_tls_close_during_connect_is_explained(cert_file: str | None) -> None:
    from types import SimpleNamespace

    from plcstack.north.mqtt_errors import connect_error

    eof = OSError("EOF occurred in violation of protocol (_ssl.c:2427)")
    settings = SimpleNamespace(cert_file=cert_file)
    error = connect_error(eof, [], broker="mqtts://b:8883", connected=False, settings=settings)
    assert isinstance(error, ConnectFailed)
    assert "EOF occurred in violation of protocol" in error.message  # the evidence stays
    if cert_file:
        assert "rejected our client certificate" in error.message and cert_file in error.message
    else:
        assert "set [mqtt] cert_file and key_file" in error.message
    # a session that was up and then closed is a lost connection, not a certificate question
    lost = connect_error(eof, [], broker="mqtts://b:8883", connected=True, settings=settings)
    assert "certificate" not in lost.message


@pytest.mark.parametrize("cert_file", [None, "/etc/plc/line1.crt"])
def test_the_alert_and_the_close_of_one_certificate_problem_are_one_reason(
    cert_file: str | None,
) -> None:
    """Under TLS 1.3 the broker's alert or only its close reaches us (a race): from one attempt
    to the next the same missing or rejected certificate reads either way, and the sink logs a
    reason once, so both must be one reason; a dropped session stays another."""
    from types import SimpleNamespace

    from plcstack.north.mqtt_errors import connect_error, reason_of

    settings = SimpleNamespace(cert_file=cert_file)
    alert = "CERTIFICATE_REQUIRED" if cert_file is None else "TLSV1_ALERT_UNKNOWN_CA"
    eof = OSError("EOF occurred in violation of protocol (_ssl.c:2427)")
    told = OSError(f"[SSL: {alert}] tlsv13 alert (_ssl.c:2580)")
    closed, alerted, lost = (
        connect_error(exc, [], broker="mqtts://b:8883", connected=up, settings=settings)
        for exc, up in ((eof, False), (told, False), (eof, True))
    )
    assert str(closed) != str(alerted)  # two wordings...
    assert reason_of(closed) == reason_of(alerted)  # ...one reason
    assert reason_of(lost) != reason_of(closed)


async def test_unusable_certificate_files_fail_at_start(tls_broker: TlsBroker) -> None:
    missing = tls_broker.settings(cert_file="/nonexistent/line1.crt", key_file="/nonexistent/k")
    with pytest.raises(ConfigError) as raised:
        await MqttSink(missing).start()
    assert str(raised.value).startswith(f"MQTT broker {tls_broker.url}: connect: TLS: ")
    assert "/nonexistent/line1.crt" in str(raised.value)
    # a key that does not belong to the certificate
    other_cert, _ = tls_broker.authority.issue(tls_broker.client_cert.parent, "x", server=False)
    mismatched = tls_broker.settings(cert_file=str(other_cert), key_file=str(tls_broker.client_key))
    with pytest.raises(ConfigError, match="cannot load the client certificate"):
        await MqttSink(mismatched).start()
    with pytest.raises(ConfigError, match="cannot load ca_file"):
        await MqttSink(parse_mqtt({"url": tls_broker.url, "ca_file": "/nonexistent"})).start()


@pytest.fixture
def login_broker(tmp_path: Path) -> Iterator[Mosquitto]:
    """mosquitto that takes user ``line1`` with password ``s3cret`` and nobody else."""
    passwords = tmp_path / "passwords"
    subprocess.run(
        ["mosquitto_passwd", "-b", "-c", str(passwords), "line1", "s3cret"],
        check=True,
        capture_output=True,
    )
    passwords.chmod(0o600)
    broker = started(Mosquitto(extra_config=f"allow_anonymous false\npassword_file {passwords}\n"))
    try:
        yield broker
    finally:
        broker.close()


def login_settings(broker: Mosquitto) -> Any:
    return parse_mqtt(
        {
            "url": broker.url,
            "username_env": "PLCSTACK_TEST_MQTT_USER",
            "password_env": "PLCSTACK_TEST_MQTT_PASSWORD",
            "reconnect_max": 0.2,
            "timeout": 1,
        }
    )


async def test_credentials_come_from_the_environment_when_the_sink_connects(
    login_broker: Mosquitto,
) -> None:
    settings = login_settings(login_broker)  # parsed without the variables: fine
    env = {"PLCSTACK_TEST_MQTT_USER": "line1", "PLCSTACK_TEST_MQTT_PASSWORD": "s3cret"}
    sink = MqttSink(settings, env=env)
    await sink.start()
    try:
        await sink.wait_connected(10)
    finally:
        await sink.aclose()
    wrong = MqttSink(settings, env={**env, "PLCSTACK_TEST_MQTT_PASSWORD": "guess"})
    error = await refused(wrong, "the broker refused the login")
    assert str(error).startswith(f"MQTT broker {login_broker.url}: connect: ")
    unset = MqttSink(settings, env={"PLCSTACK_TEST_MQTT_USER": "line1"})
    with pytest.raises(ConfigError) as missing:
        await unset.start()
    assert str(missing.value) == (
        f"MQTT broker {login_broker.url}: connect: [mqtt] password_env names the environment "
        "variable 'PLCSTACK_TEST_MQTT_PASSWORD', which is not set; not connecting"
    )


CONFIG = """
[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:1"
[plc.tags]
strokes = "D100"
[mqtt]
url = "{url}"
username_env = "PLCSTACK_TEST_MQTT_USER"
password_env = "PLCSTACK_TEST_MQTT_PASSWORD"
"""


def test_loading_a_config_needs_no_credentials_but_polling_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("PLCSTACK_TEST_MQTT_USER", raising=False)
    monkeypatch.delenv("PLCSTACK_TEST_MQTT_PASSWORD", raising=False)
    path = tmp_path / "plant.toml"
    port = free_port()
    path.write_text(CONFIG.format(url=f"mqtt://127.0.0.1:{port}"))
    config = load_config(path)  # a tool that only reads the file needs no secrets
    assert config.north.mqtt is not None
    assert config.north.mqtt.username_env == "PLCSTACK_TEST_MQTT_USER"
    code = main(["poll", str(path), "--format", "none", "--duration", "5"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err == (
        f"plcstack: error: MQTT broker mqtt://127.0.0.1:{port}: connect: [mqtt] username_env names"
        " the environment variable 'PLCSTACK_TEST_MQTT_USER', which is not set; not connecting\n"
    )


def test_relative_paths_in_mqtt_are_relative_to_the_toml_file(
    tls_broker: TlsBroker, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    site = tmp_path / "site"
    site.mkdir()
    for source, name in [
        (tls_broker.authority.ca, "ca.pem"),
        (tls_broker.client_cert, "line1.crt"),
        (tls_broker.client_key, "line1.key"),
    ]:
        (site / name).write_bytes(source.read_bytes())
    (site / "plant.toml").write_text(
        f"""
[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:1"
[plc.tags]
strokes = "D100"
[mqtt]
url = "{tls_broker.url}"
mode = "sparkplug"
client_id = "edge-relative"
ca_file = "ca.pem"
cert_file = "line1.crt"
key_file = "line1.key"
buffer_path = "queue.sqlite"
"""
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # a service's working directory is rarely the config's
    assert main(["poll", str(site / "plant.toml"), "--format", "none", "--duration", "1.5"]) == 0
    assert (site / "queue.sqlite").exists() and (site / "queue.sparkplug.json").exists()
    assert list(elsewhere.iterdir()) == []
    # the broker took the certificate found next to the file
    assert "as edge-relative" in tls_broker.broker.log()
