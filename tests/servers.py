"""Real servers for tests: mosquitto, nats-server (JetStream) and InfluxDB 1.x on free loopback
ports.

Tests of the north side talk to the real brokers a plant runs, not to fakes, so a test that needs
one starts it here. If the binary is missing or the server does not come up, the helper raises
``ServerUnavailable`` with the reason (and the server's log); the fixtures turn that into a test
*failure*, never a skip: a CI machine without mosquitto must not pass the MQTT tests silently.
``scripts/setup-test-machine`` installs the Debian packages.

Usage (the fixtures ``mosquitto`` and ``influxd`` are registered in ``tests/conftest.py``)::

    from tests.servers import Mosquitto

    def test_x(mosquitto: Mosquitto) -> None:
        url = mosquitto.url               # "mqtt://127.0.0.1:PORT"
        mosquitto.stop()                  # broker gone: clients see the connection drop
        mosquitto.start()                 # same port again, same persistence directory
        mosquitto.restart()               # both

The port is picked once (``tests.ports.free_port``: reserved for this process, outside the range
the kernel hands out) and kept across ``restart()`` so clients reconnect to the same address.
With ``persistence=True`` (the default) the broker keeps persistent sessions and their queued
QoS 1/2 messages across a restart (it saves its database on SIGTERM), which is what a
store-and-forward test needs from the subscriber side.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Self

import pytest

from tests.ports import free_port

__all__ = [
    "Influxd",
    "Mosquitto",
    "NatsServer",
    "ServerUnavailable",
    "free_port",
    "influxd",
    "mosquitto",
    "nats_server",
]

#: how long a server may take to accept connections after start
START_TIMEOUT = 10.0


class ServerUnavailable(RuntimeError):
    """The server binary is missing or did not come up; the message says why."""


def _accepts(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


_PACKAGES = {"mosquitto": "mosquitto", "nats-server": "nats-server", "influxd": "influxdb"}


def _find(binary: str, *extra_dirs: str) -> str:
    path = shutil.which(binary)
    if path is None:
        for d in extra_dirs:
            candidate = os.path.join(d, binary)
            if os.access(candidate, os.X_OK):
                return candidate
        raise ServerUnavailable(
            f"{binary} is not installed (Debian: apt-get install -y "
            f"{_PACKAGES.get(binary, binary)}); scripts/setup-test-machine installs it"
        )
    return path


class _Server:
    """A subprocess server on fixed loopback ports in its own temporary directory."""

    name = "server"

    def __init__(self) -> None:
        self.host = "127.0.0.1"
        self.port = free_port()
        self._tmp = tempfile.TemporaryDirectory(prefix=f"plcstack-{self.name}-")
        self.dir = Path(self._tmp.name)
        self.log_path = self.dir / f"{self.name}.log"
        self._proc: subprocess.Popen[bytes] | None = None

    # -- subclass hooks -------------------------------------------------------------------------
    def _command(self) -> list[str]:
        raise NotImplementedError

    def _ready(self) -> bool:
        return _accepts(self.host, self.port)

    # -- lifecycle ------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def log(self) -> str:
        """The server's log so far (for failure messages)."""
        try:
            return self.log_path.read_text(errors="replace")[-4000:]
        except OSError:
            return ""

    def start(self) -> None:
        """Start the server and wait until it accepts connections; ``ServerUnavailable`` if not."""
        if self.running:
            return
        command = self._command()
        log = open(self.log_path, "ab")  # noqa: SIM115 - handed to the child, closed below
        try:
            self._proc = subprocess.Popen(
                command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
            )
        except OSError as exc:
            raise ServerUnavailable(f"{self.name}: cannot run {command[0]}: {exc}") from exc
        finally:
            log.close()
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                code = self._proc.returncode
                self._proc = None
                raise ServerUnavailable(
                    f"{self.name} exited with code {code} on {self.host}:{self.port}; "
                    f"log:\n{self.log()}"
                )
            if self._ready():
                return
            time.sleep(0.02)
        self.stop()
        raise ServerUnavailable(
            f"{self.name} did not accept connections on {self.host}:{self.port} within "
            f"{START_TIMEOUT:.0f} s; log:\n{self.log()}"
        )

    def stop(self) -> None:
        """Stop the server (SIGTERM, so it saves its state; SIGKILL after 5 s)."""
        proc, self._proc = self._proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
        # The port must be free again before a restart binds it (no TIME_WAIT issue for
        # listeners with SO_REUSEADDR, which both servers set, but wait for the close).
        deadline = time.monotonic() + 5
        while _accepts(self.host, self.port) and time.monotonic() < deadline:
            time.sleep(0.02)

    def restart(self) -> None:
        self.stop()
        self.start()

    def close(self) -> None:
        """Stop and remove the temporary directory."""
        self.stop()
        with contextlib.suppress(OSError):
            self._tmp.cleanup()

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class Mosquitto(_Server):
    """A mosquitto broker on ``127.0.0.1:port``, anonymous, optionally persistent."""

    name = "mosquitto"

    def __init__(self, *, persistence: bool = True, extra_config: str = "") -> None:
        super().__init__()
        self.persistence = persistence
        self.extra_config = extra_config
        self.binary = _find("mosquitto", "/usr/sbin", "/usr/local/sbin")

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    def _ready(self) -> bool:
        """Every listener accepts, also those of ``extra_config`` (a TLS listener comes up after
        the plain one: a test that connects to it at once was refused now and then)."""
        ports = [self.port] + [
            int(line.split()[1])
            for line in self.extra_config.splitlines()
            if line.startswith("listener ") and len(line.split()) > 1
        ]
        return all(_accepts(self.host, port) for port in ports)

    def _command(self) -> list[str]:
        conf = self.dir / "mosquitto.conf"
        lines = [
            f"listener {self.port} {self.host}",
            "allow_anonymous true",
            f"persistence {'true' if self.persistence else 'false'}",
            f"persistence_location {self.dir}/",
            # Keep every queued message of an offline persistent session (the default cap of
            # 1000 would drop replayed data in a test that buffers more than that).
            "max_queued_messages 0",
            # run as root (CI), mosquitto would switch to the user "mosquitto", which cannot
            # write the persistence file into our temporary directory: stay who we are
            *([f"user {pwd.getpwuid(os.geteuid()).pw_name}"] if os.geteuid() == 0 else []),
            "log_type error",
            "log_type warning",
            "log_type notice",
            self.extra_config,
        ]
        conf.write_text("\n".join(lines) + "\n")
        return [self.binary, "-c", str(conf)]


class NatsServer(_Server):
    """nats-server with JetStream (``-js``) on ``127.0.0.1:port``, its store in the temporary
    directory (kept across ``restart()``), and the HTTP monitor on ``monitor_port`` (``/varz``
    counts messages for the scale-out figures; ``/healthz`` says when JetStream is ready)."""

    name = "nats-server"

    def __init__(self) -> None:
        super().__init__()
        self.monitor_port = free_port()
        self.binary = _find("nats-server", "/usr/sbin", "/usr/local/sbin", "/usr/bin")

    @property
    def url(self) -> str:
        return f"nats://{self.host}:{self.port}"

    def varz(self) -> dict[str, object]:
        """The server's ``/varz`` statistics (in_msgs, out_msgs, connections, ...)."""
        import json
        import urllib.request

        with urllib.request.urlopen(f"http://{self.host}:{self.monitor_port}/varz", timeout=2) as r:
            data: dict[str, object] = json.load(r)
            return data

    def _ready(self) -> bool:
        import urllib.request

        if not _accepts(self.host, self.port):
            return False
        try:
            url = f"http://{self.host}:{self.monitor_port}/healthz?js-enabled-only=true"
            with urllib.request.urlopen(url, timeout=0.5) as r:
                return int(r.status) == 200
        except OSError:
            return False

    def _command(self) -> list[str]:
        return [
            self.binary,
            "-js",
            "-a",
            self.host,
            "-p",
            str(self.port),
            "-m",
            str(self.monitor_port),
            "-sd",
            str(self.dir / "jetstream"),
            "-l",
            str(self.log_path),
        ]


class Influxd(_Server):
    """InfluxDB 1.x (``influxd``) with HTTP on ``127.0.0.1:port``, everything else loopback.

    ``auth=True``: HTTP authentication on, with one admin user ``admin``/``secret`` (created
    through the query that InfluxDB allows while it has no user at all); :meth:`request` then
    sends those credentials."""

    name = "influxd"
    USER, PASSWORD = "admin", "secret"

    def __init__(self, *, auth: bool = False) -> None:
        super().__init__()
        self.auth = auth
        self.bind_port = free_port()
        self.binary = _find("influxd", "/usr/bin", "/usr/local/bin")

    def start(self) -> None:
        super().start()
        if self.auth:
            status, text = self._request(
                "POST",
                "/query?q="
                + urllib.parse.quote(
                    f"CREATE USER {self.USER} WITH PASSWORD '{self.PASSWORD}' WITH ALL PRIVILEGES"
                ),
                b"",
                credentials=False,
            )
            # after a restart the user exists already: then only an authorised query works
            created = status == 200 and '"error"' not in text
            if not created and status not in (401, 403):
                raise ServerUnavailable(f"influxd: CREATE USER: {status} {text}")

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def _ready(self) -> bool:
        import urllib.request

        try:
            with urllib.request.urlopen(f"{self.url}/ping", timeout=0.5) as r:
                return int(r.status) == 204
        except OSError:
            return False

    def request(self, method: str, path: str, body: bytes = b"") -> tuple[int, str]:
        """One HTTP request to influxd: (status, body text); HTTP errors are returned."""
        return self._request(method, path, body, credentials=self.auth)

    def _request(
        self, method: str, path: str, body: bytes, *, credentials: bool
    ) -> tuple[int, str]:
        import base64
        import urllib.error
        import urllib.request

        req = urllib.request.Request(f"{self.url}{path}", data=body or None, method=method)
        if credentials:
            token = base64.b64encode(f"{self.USER}:{self.PASSWORD}".encode()).decode()
            req.add_header("Authorization", f"Basic {token}")
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return int(r.status), r.read().decode()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read().decode()

    def create_database(self, name: str) -> None:
        """CREATE DATABASE and wait until a write to it is no longer "database not found"."""
        status, text = self.request(
            "POST", "/query?q=" + urllib.parse.quote(f'CREATE DATABASE "{name}"')
        )
        if status != 200 or '"error"' in text:
            raise ServerUnavailable(f"influxd: CREATE DATABASE {name}: {status} {text}")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            status, text = self.request("GET", "/query?q=SHOW+DATABASES")
            if f'"{name}"' in text:
                return
            time.sleep(0.05)
        raise ServerUnavailable(f"influxd: database {name} did not appear: {text}")

    def _command(self) -> list[str]:
        conf = self.dir / "influxdb.conf"
        d = self.dir
        conf.write_text(
            f'reporting-disabled = true\nbind-address = "{self.host}:{self.bind_port}"\n'
            f'[meta]\n  dir = "{d}/meta"\n'
            f'[data]\n  dir = "{d}/data"\n  wal-dir = "{d}/wal"\n  query-log-enabled = false\n'
            f'[http]\n  enabled = true\n  bind-address = "{self.host}:{self.port}"\n'
            f"  log-enabled = false\n  auth-enabled = {'true' if self.auth else 'false'}\n"
            "[monitor]\n  store-enabled = false\n"
            "[subscriber]\n  enabled = false\n"
            "[continuous_queries]\n  enabled = false\n"
            "[[graphite]]\n  enabled = false\n[[collectd]]\n  enabled = false\n"
            "[[opentsdb]]\n  enabled = false\n[[udp]]\n  enabled = false\n"
        )
        return [self.binary, "-config", str(conf)]


def _serve(server: _Server) -> Iterator[_Server]:
    try:
        server.start()
    except ServerUnavailable as exc:
        server.close()
        pytest.fail(str(exc), pytrace=False)
    try:
        yield server
    finally:
        server.close()


@pytest.fixture
def mosquitto() -> Iterator[Mosquitto]:
    """A fresh persistent mosquitto on a free loopback port; the test fails if there is none."""
    for server in _serve(Mosquitto()):
        assert isinstance(server, Mosquitto)
        yield server


@pytest.fixture
def nats_server() -> Iterator[NatsServer]:
    """A fresh nats-server with JetStream on a free loopback port; the test fails if there is
    none."""
    for server in _serve(NatsServer()):
        assert isinstance(server, NatsServer)
        yield server


@pytest.fixture
def influxd() -> Iterator[Influxd]:
    """A fresh InfluxDB 1.x on free loopback ports; the test fails if there is none."""
    for server in _serve(Influxd()):
        assert isinstance(server, Influxd)
        yield server
