"""MQTT sink: scans out, writes in, over aiomqtt with our own reconnect and store-and-forward.

aiomqtt (on paho-mqtt) is one connection per ``async with Client(...)`` and never reconnects by
itself; this module is the loop around it:

* connect (Last Will = the poller's ``offline`` status, retained), publish the layout's
  on-connect messages (``online``; Sparkplug NBIRTH/DBIRTH), subscribe to write requests;
* two tasks per connection: the reader (write requests; aiomqtt's message iterator raises when
  the connection drops, which ends the connection's task group) and the publisher, which sends
  the oldest messages of the :class:`StoreAndForward` queue and removes them only once the
  broker acknowledged them (QoS >= 1);
* on any failure: wait a jittered, growing backoff, then a new Client (a fresh paho session, so
  nothing is resent twice behind our back) and the backlog again, oldest first.

:meth:`MqttSink.submit` never blocks and never touches the network: the poller's consumer hands
over scans, the layout turns each into its messages, the queue takes them (memory, then disk).

Delivery is at least once: messages in flight when a connection drops are sent again, so a
subscriber may see the last window (``inflight``, default 64) twice, always in order. With
``qos = 0`` the broker acknowledges nothing and messages sent just before a drop can be lost;
use QoS 1 (the default) for store-and-forward.

Writes: a request on ``P/PLC/write/req`` goes through the poller's single-flight ``write_tag``
(the same rules as a write from Python) and is answered on ``P/PLC/write/resp`` with ``ok`` or
the reason; see :mod:`plcstack.north.layout`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import socket
import ssl
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from plcstack.checks import Table
from plcstack.errors import ConfigError, PlcError
from plcstack.north.buffer import Message, StoreAndForward, buffer_keys, forwarding_health
from plcstack.north.face import PlcUpdate
from plcstack.north.health import Condition, Health
from plcstack.north.layout import (
    JsonLayout,
    MqttLayout,
    Publish,
    Unanswerable,
    WriteRequest,
    topic_level,
    write_response_payload,
    write_response_topic,
)
from plcstack.north.mqtt_client import guarded_client
from plcstack.north.mqtt_errors import PahoLog, connect_error, reason_of
from plcstack.north.supervise import Supervised, Supervisor
from plcstack.north.writes import BAD_REQUEST, BUSY, UNKNOWN_PLC, WritePath
from plcstack.poll.samples import Sample, Scan
from plcstack.transports.backoff import Backoff

if TYPE_CHECKING:
    from prometheus_client.core import Metric

__all__ = ["MqttSettings", "MqttSink", "parse_mqtt"]

log = logging.getLogger("plcstack.north.mqtt")

#: write requests waiting for their PLC at once; more are refused with ``busy``
MAX_PENDING_WRITES = 256


@dataclass(frozen=True)
class MqttSettings:
    """The ``[mqtt]`` table (see :func:`parse_mqtt`)."""

    host: str = "127.0.0.1"
    port: int = 1883
    tls: bool = False
    client_id: str = "plcstack"
    prefix: str = "plcstack"
    qos: int = 1
    #: QoS of Sparkplug births, data and deaths: 0 as Sparkplug 3.0 requires, 1 a deviation
    #: that has the broker acknowledge each (the store-and-forward queue then re-sends what a
    #: dropped connection left unacknowledged)
    sparkplug_qos: int = 0
    mode: str = "json"
    group_id: str = "plcstack"
    #: literal credentials (Python API); a TOML file names environment variables instead
    username: str | None = field(default=None, repr=False)
    password: str | None = field(default=None, repr=False)
    #: environment variables read when the sink starts connecting, not when the file is loaded:
    #: a tool that only loads or checks the configuration needs no secrets
    username_env: str | None = None
    password_env: str | None = None
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    keepalive: int = 30
    #: seconds to wait for the broker's CONNACK (and for each acknowledgement)
    timeout: float = 10.0
    buffer_path: str | None = None
    #: Sparkplug: where bdSeq survives a restart (default: next to buffer_path)
    state_path: str | None = None
    buffer_memory: int = 4 << 20
    buffer_max: int = 256 << 20
    inflight: int = 64
    reconnect_max: float = 30.0

    @property
    def url(self) -> str:
        """The broker as a URL, for messages (``mqtts://broker:8883``)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'mqtts' if self.tls else 'mqtt'}://{host}:{self.port}"

    def credentials(self, env: Mapping[str, str] | None = None) -> tuple[str | None, str | None]:
        """(username, password) for the CONNECT: literal values, else the named environment
        variables (``env``, default ``os.environ``), read now.

        :class:`ConfigError` naming the broker and the variable if one is not set: nothing is
        sent to the broker without the credentials the configuration asks for.
        """
        env = os.environ if env is None else env
        out: list[str | None] = []
        for key, literal, var in (
            ("username", self.username, self.username_env),
            ("password", self.password, self.password_env),
        ):
            if literal is not None or var is None:
                out.append(literal)
            elif var in env:
                out.append(env[var])
            else:
                raise ConfigError(
                    f"[mqtt] {key}_env names the environment variable {var!r}, which is not set;"
                    " not connecting",
                    plc=f"MQTT broker {self.url}",
                    request="connect",
                )
        return out[0], out[1]


_MQTT_KEYS = frozenset({
    "url", "client_id", "prefix", "qos", "mode", "group_id", "username_env", "password_env",
    "ca_file", "cert_file", "key_file", "keepalive", "buffer_path", "buffer_memory",
    "buffer_max", "inflight", "reconnect_max", "state_path", "timeout", "sparkplug_qos",
})  # fmt: skip


def parse_mqtt(table: object, *, base: Path | None = None) -> MqttSettings:
    """The ``[mqtt]`` table of the poll TOML (``base``: the file's directory, against which
    relative ``ca_file``, ``cert_file``, ``key_file``, ``buffer_path`` and ``state_path`` are
    taken, as ``[opcua]`` takes its certificates; None: as written)::

    [mqtt]
    url = "mqtt://broker:1883"      # mqtts:// = TLS (port 8883 by default)
    client_id = "plcstack-line1"
    prefix = "plcstack"             # first topic level (JSON mode)
    qos = 1                         # data messages; status and responses always 1
    mode = "json"                   # or "sparkplug" (Sparkplug B, spBv1.0 topics)
    sparkplug_qos = 0               # Sparkplug births, data, deaths: 0 as Sparkplug 3.0 says;
                                    # 1 (a deviation) has the broker acknowledge each message
    group_id = "plant1"             # Sparkplug group id; the edge node id is client_id
    username_env = "MQTT_USER"      # credentials come from the environment, never the file;
    password_env = "MQTT_PASSWORD"  # read when the sink connects (MqttSettings.credentials)
    ca_file = "/etc/ssl/broker-ca.pem"   # TLS: CA, and a client certificate if needed
    cert_file = "..."
    key_file = "..."
    buffer_path = "/var/lib/plcstack/mqtt.sqlite"   # store-and-forward on disk
    buffer_memory = 4194304         # bytes in memory before spilling to disk
    buffer_max = 268435456          # total backlog budget; the oldest beyond it are dropped
    state_path = "/var/lib/plcstack/sparkplug.json"  # Sparkplug bdSeq across restarts
                                    # (default: next to buffer_path, e.g. mqtt.sparkplug.json)
    """
    t = Table.of(table, "mqtt", base=base)
    t.keys(_MQTT_KEYS)
    url = t.url("url", "mqtt://127.0.0.1:1883", ("mqtt", "mqtts"))
    tls = url.scheme == "mqtts"
    port = url.port or (8883 if tls else 1883)
    mode = t.choice("mode", "json", ("json", "sparkplug"))
    prefix = t.text("prefix", "plcstack")
    if any(c in prefix for c in "+#\x00"):
        raise t.error("prefix", "must not contain + # or NUL")
    if "key_file" in t and "cert_file" not in t:
        raise t.error("key_file", "needs cert_file (the client certificate it belongs to)")
    return MqttSettings(
        host=url.host,
        port=port,
        tls=tls or "ca_file" in t or "cert_file" in t,
        client_id=t.text("client_id", "plcstack"),
        prefix=prefix,
        qos=t.integer("qos", 1, 0, 2),
        sparkplug_qos=t.integer("sparkplug_qos", 0, 0, 1),
        mode=mode,
        group_id=t.text("group_id", "plcstack"),
        username_env=t.optional_text("username_env"),
        password_env=t.optional_text("password_env"),
        ca_file=t.file("ca_file"),
        cert_file=t.file("cert_file"),
        key_file=t.file("key_file"),
        keepalive=t.integer("keepalive", 30, 5, 3600),
        timeout=t.seconds("timeout", 10.0, lo=0.5, hi=300),
        state_path=t.file("state_path"),
        **buffer_keys(t),
        inflight=t.integer("inflight", 64, 1, 65535),
        reconnect_max=t.seconds("reconnect_max", 30.0, lo=0.1, hi=3600),
    )


@dataclass
class SinkStats:
    """Counters of the sink (also exported by the metrics endpoint)."""

    submitted: int = 0  # messages handed to the queue
    sent: int = 0  # messages acknowledged by the broker (QoS >= 1) or written (QoS 0)
    buffered: int = 0  # messages queued while no connection was up
    replayed: int = 0  # messages sent after a reconnect that had waited for it
    connects: int = 0
    disconnects: int = 0
    failures: int = 0  # connection attempts that failed and sessions that dropped
    writes_ok: int = 0
    writes_refused: int = 0


class MqttSink:
    """Publishes scans through a :class:`StoreAndForward` queue; answers write requests.

    ``layout``: JSON (default) or Sparkplug B (:class:`~plcstack.north.layout.MqttLayout`);
    ``writes``: the run's one write path (default: none, every write refused ``not_writable``);
    ``supervisor``: the run's, under which the connection task runs (default: its own);
    ``env``: where ``username_env``/``password_env`` are looked up (default ``os.environ``),
    when the sink starts.
    """

    def __init__(
        self,
        settings: MqttSettings,
        *,
        layout: MqttLayout | None = None,
        writes: WritePath | None = None,
        supervisor: Supervisor | None = None,
        buffer: StoreAndForward | None = None,
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.settings = settings
        self.env = env
        #: credentials and TLS context, resolved by :meth:`prepare` (at start, not at load)
        self._prepared: tuple[str | None, str | None, ssl.SSLContext | None] | None = None
        #: why the latest connection attempt failed or the session dropped (a ConnectFailed or
        #: ConnectionLost naming the broker); None before the first failure
        self.last_error: PlcError | None = None
        self._paho_log = PahoLog()
        self.writes = writes if writes is not None else WritePath(None)
        # the default: JSON, taking write requests for the PLCs the write path can write
        plcs = self.writes.poller.plcs if self.writes.poller is not None else []
        self.layout: MqttLayout = (
            layout
            if layout is not None
            else JsonLayout(settings.prefix, settings.client_id, settings.qos, plcs=plcs)
        )
        self.buffer = buffer if buffer is not None else StoreAndForward.configured(settings)
        self.stats = SinkStats()
        self.connected = False
        #: the broker connection's health: not connected since when, and why
        self.link = Condition(self.name)
        self._wake = asyncio.Event()
        self._closing = False
        self._client: Any = None  # the aiomqtt client of the current connection
        self._replay_until = -1
        self._writes: set[asyncio.Task[None]] = set()
        self.supervisor = supervisor if supervisor is not None else Supervisor()
        self._task: Supervised | None = None
        self._connected_event = asyncio.Event()
        self._idle = asyncio.Event()  # set while the publisher has nothing to send

    @property
    def name(self) -> str:
        """The sink's name in logs, metrics and ``/healthz``: ``mqtt`` or ``sparkplug``."""
        return "sparkplug" if self.settings.mode == "sparkplug" else "mqtt"

    # -- in: scans ------------------------------------------------------------------------------
    def submit(self, scans: Sequence[Scan]) -> None:
        """Queue the messages for these scans (never blocks, never raises for the network).

        All or nothing: every message is encoded before the first is queued, so a sample the
        layout cannot encode raises with nothing queued, and the supervisor's retry without it
        queues nothing twice.
        """
        if not scans:
            return
        for message in self.layout.messages(scans):
            self._put(message)

    def probe(self, sample: Sample) -> None:
        """Raise if the layout cannot encode ``sample``; queues nothing, changes no state."""
        self.layout.probe(sample)

    async def update_plcs(self, update: PlcUpdate) -> None:
        """The PLCs a reload changed: the layout's messages about them (a removed PLC's
        ``offline`` status or DDEATH, an added one's DBIRTH) join the queue after what
        waits, so a subscriber sees them in order with the data."""
        for message in self.layout.update_plcs(update, time.time()):
            self._put(message)

    def _put(self, message: Publish) -> None:
        self.buffer.put(*message)
        self.stats.submitted += 1
        if not self.connected:
            self.stats.buffered += 1
        self._idle.clear()
        self._wake.set()

    def summary(self) -> str:
        """One line for stderr at the end of a run: what was sent, what was not, and where."""
        waiting = len(self.buffer)
        where = ""
        if waiting:
            path = self.settings.buffer_path
            where = f" (kept in {path} for the next run)" if path else " (lost: no buffer_path)"
        buffer = self.buffer
        dropped = f"{buffer.dropped} dropped by buffer_max"
        if buffer.lost_to_disk:
            dropped = (
                f"{buffer.dropped - buffer.lost_to_disk} dropped by buffer_max,"
                f" {buffer.lost_to_disk} lost because the disk refused them"
            )
        return (
            f"{self.name} {self.settings.url}: {self.stats.sent} sent, {waiting} not delivered"
            f"{where}, {dropped}"
        )

    def health(self) -> Health:
        """Unhealthy while the broker is not connected (since when, why, how many messages
        wait) or the queue reports a problem of its own (a full disk)."""
        return forwarding_health(self.link, self.buffer, "messages")

    def announce(self) -> str | None:
        return None

    def metrics(self) -> Iterator[Metric]:
        """None of its own: the run's collector exports the queue and the connection."""
        return iter(())

    # -- lifecycle ------------------------------------------------------------------------------
    def prepare(self) -> None:
        """Read the credentials from the environment and load the TLS files, once.

        Raises :class:`ConfigError` naming the broker and what is missing (an environment
        variable, a certificate file, a key that does not match): problems no retry can fix, so
        ``start`` fails instead of retrying them forever.
        """
        if self._prepared is None:
            username, password = self.settings.credentials(self.env)
            self._prepared = (username, password, self._tls_context())

    async def start(self) -> None:
        self.prepare()
        self.link.fail(f"not connected to the MQTT broker {self.settings.url} yet")
        self._task = self.supervisor.start(self.name, self.run)

    async def wait_connected(self, timeout: float) -> None:
        """Wait for a connection; after ``timeout`` raise why the last attempt failed (a
        :class:`ConnectFailed` naming the broker), or ``TimeoutError`` if none failed yet."""
        try:
            async with asyncio.timeout(timeout):
                await self._connected_event.wait()
        except TimeoutError:
            error = self.last_error
            if error is None:
                raise
            raise type(error)(error.message, plc=error.plc, request=error.request) from None

    async def wait_drained(self, timeout: float) -> None:
        """Wait until everything queued so far was sent (``TimeoutError`` after ``timeout``)."""
        async with asyncio.timeout(timeout):
            while len(self.buffer):
                self._idle.clear()
                await self._idle.wait()

    async def aclose(self, *, drain: float = 2.0) -> None:
        """Send what can be sent within ``drain`` s, say ``offline``, keep the rest on disk."""
        if self._task is not None and self.connected and drain > 0:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(drain):
                    await self._idle.wait()
        self._closing = True
        client = self._client
        if client is not None and self.connected:
            with contextlib.suppress(Exception):
                async with asyncio.timeout(2):
                    for topic, payload, qos, retain in self.layout.on_close(time.time()):
                        await client.publish(topic, payload, qos=qos, retain=retain)
        if self._task is not None:
            # cancels until the task has really ended (aiomqtt awaits PUBACK/SUBACK through
            # Python 3.11's wait_for, which can swallow one cancellation)
            await self._task.stop()
        for task in list(self._writes):
            task.cancel()
        self.buffer.close()

    async def run(self) -> None:
        """Connect, serve, reconnect with backoff; until cancelled."""
        import aiomqtt

        self.prepare()
        backoff = Backoff(initial=0.1, maximum=self.settings.reconnect_max)
        while not self._closing:
            self._paho_log.lines.clear()
            try:
                await self._session(aiomqtt, backoff)
            except* (aiomqtt.MqttError, OSError) as group:
                self._failed(group.exceptions[0])
            was = self.connected
            self.connected = False
            self._client = None
            self._connected_event.clear()
            if was:
                self.stats.disconnects += 1
            await asyncio.sleep(backoff.next_delay())

    def _failed(self, exc: BaseException) -> None:
        """Note why the attempt or session ended; log it once per distinct reason (a broker
        that stays away is one WARNING, not one every backoff)."""
        error = connect_error(
            exc,
            self._paho_log.lines,
            broker=f"MQTT broker {self.settings.url}",
            connected=self.connected,
            settings=self.settings,
        )
        self.stats.failures += 1
        previous, self.last_error = self.last_error, error
        self.link.fail(str(error))
        if previous is not None and reason_of(previous) == reason_of(error):
            log.debug("%s (again)", error)
        else:
            log.warning("%s; retrying with backoff", error, extra={"face": self.name})

    def _tls_context(self) -> ssl.SSLContext | None:
        s = self.settings
        if not s.tls:
            return None
        try:
            context = ssl.create_default_context(cafile=s.ca_file)
        except (OSError, ValueError) as exc:  # ssl.SSLError is an OSError
            raise ConfigError(
                f"TLS: cannot load ca_file {s.ca_file!r}: {exc}; not connecting",
                plc=f"MQTT broker {s.url}",
                request="connect",
            ) from None
        if s.cert_file:
            try:
                context.load_cert_chain(s.cert_file, s.key_file)
            except (OSError, ValueError) as exc:
                key = f" with key_file {s.key_file!r}" if s.key_file else " (key in the same file)"
                raise ConfigError(
                    f"TLS: cannot load the client certificate cert_file {s.cert_file!r}{key}: "
                    f"{exc}; not connecting",
                    plc=f"MQTT broker {s.url}",
                    request="connect",
                ) from None
        return context

    async def _session(self, aiomqtt: ModuleType, backoff: Backoff) -> None:
        s = self.settings
        assert self._prepared is not None
        username, password, tls_context = self._prepared
        will_topic, will_payload = self.layout.will(time.time())
        client = guarded_client(aiomqtt)(
            s.host,
            s.port,
            identifier=s.client_id,
            username=username,
            password=password,
            will=aiomqtt.Will(will_topic, will_payload, qos=1, retain=self.layout.will_retain),
            clean_session=True,
            keepalive=s.keepalive,
            timeout=s.timeout,
            logger=self._paho_log,
            tls_context=tls_context,
            max_inflight_messages=s.inflight,
            # small messages and PUBACKs both ways: Nagle plus delayed ACK would hold each
            # window for tens of milliseconds
            socket_options=[(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)],
        )
        # a full window of publishes in flight is normal here, not a reason for aiomqtt's warning
        client.pending_calls_threshold = s.inflight + 16
        async with client:
            self._client = client
            self.connected = True
            self.stats.connects += 1
            self.link.clear()
            if self.last_error is not None:  # it was lost: say it is back, once
                log.warning(
                    "%s: connected to %s again; %d messages waiting are sent first",
                    self.name,
                    s.url,
                    len(self.buffer),
                    extra={"face": self.name},
                )
                self.last_error = None  # the next failure is a change again, logged
            backoff.reset()
            # everything queued before this point waited for the connection
            self._replay_until = self.buffer.next_seq - 1
            for topic, payload, qos, retain in self.layout.on_connect(time.time()):
                await client.publish(topic, payload, qos=qos, retain=retain)
            for topic in self.layout.subscriptions():
                await client.subscribe(topic, qos=1)
            self._connected_event.set()
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self._reader(client))
                tg.create_task(self._publisher(client))

    async def _publisher(self, client: Any) -> None:
        """A sliding window: up to ``inflight`` publishes outstanding, removed in order.

        A new message goes out as soon as the oldest is acknowledged (not in rounds that wait
        for a whole window): the stream of PUBLISH packets keeps carrying our TCP ACKs, so a
        broker without TCP_NODELAY does not stall each window on delayed ACKs.
        """
        buffer, stats = self.buffer, self.stats
        window = self.settings.inflight
        inflight: collections.deque[tuple[Message, asyncio.Task[None]]] = collections.deque()
        last_started = -1
        try:
            while True:
                room = window - len(inflight)
                if room > 0:
                    # in-flight messages are the oldest in the queue (the byte budget keeps
                    # them): skip them by seq
                    for m in buffer.peek(len(inflight) + room):
                        if m.seq > last_started:
                            task = asyncio.ensure_future(self._publish(client, m))
                            inflight.append((m, task))
                            last_started = m.seq
                    buffer.in_flight_through = last_started  # kept from the byte budget
                if not inflight:
                    self._wake.clear()
                    self._idle.set()
                    await self._wake.wait()
                    continue
                m, task = inflight[0]
                if not task.done():
                    self._wake.clear()
                    # the oldest acknowledgement, or new messages to fill the window with
                    waker = asyncio.ensure_future(self._wake.wait())
                    try:
                        await asyncio.wait((task, waker), return_when=asyncio.FIRST_COMPLETED)
                    finally:
                        waker.cancel()
                    if not task.done():
                        continue
                inflight.popleft()
                task.result()  # a failed publish ends this connection
                buffer.ack(m.seq)
                stats.sent += 1
                if m.seq <= self._replay_until:
                    stats.replayed += 1
        finally:
            buffer.in_flight_through = -1  # not acknowledged: sent again on the next connection
            for _, task in inflight:
                task.cancel()

    async def _publish(self, client: Any, m: Message) -> None:
        payload = self.layout.prepare(m, m.seq <= self._replay_until)
        if payload is None:  # the layout says this one is obsolete (an old session's birth)
            return
        await client.publish(m.topic, payload, qos=m.qos, retain=m.retain)

    # -- in: write requests ---------------------------------------------------------------------
    async def _reader(self, client: Any) -> None:
        async for message in client.messages:
            payload = message.payload
            if not isinstance(payload, bytes | bytearray):
                payload = str(payload or "").encode()
            self.handle_request(str(message.topic), bytes(payload))

    def handle_request(self, topic: str, payload: bytes) -> None:
        """Carry out what a received message asks for (the layout says what that is)."""
        for command in self.layout.commands(topic, payload):
            if isinstance(command, Publish):  # a rebirth: through the queue, after what waits
                self._put(command)
            elif isinstance(command, Unanswerable):
                self.stats.writes_refused += 1
                log.debug("%s: %s on %s; nobody to answer", self.name, command.reason, topic)
            else:
                self._request(command)

    def _request(self, request: WriteRequest) -> None:
        plc, tag = request.plc, request.tag
        refusal: tuple[str, str] | None = None
        if request.error is not None or tag is None:
            refusal = BAD_REQUEST, request.error or "bad request"
        elif plc is None:
            refusal = UNKNOWN_PLC, f"no PLC named {request.level!r} here"
        elif len(self._writes) >= MAX_PENDING_WRITES:
            refusal = BUSY, "too many writes waiting; not attempted"
        if refusal is not None:
            # logged and audited as every refused write is, then answered; no peer: the broker
            # delivers a message without its publisher's address
            self.writes.refuse(
                self.name, None, plc or request.level, tag or "", request.value, *refusal, peer=None
            )
            self._respond(request.level, request.request_id, *refusal)
            return
        task = asyncio.create_task(self._write(request))
        self._writes.add(task)
        task.add_done_callback(self._writes.discard)

    async def _write(self, request: WriteRequest) -> None:
        """One write through the run's write path (allow-list, value grammar, ``write_tag``,
        audit, log), then the answer; the source is the sink's name."""
        assert request.plc is not None and request.tag is not None
        # no peer: the broker delivers a message without its publisher's address
        result = await self.writes.write(
            self.name, None, request.plc, request.tag, request.value, peer=None
        )
        level = topic_level(request.plc)
        if result.ok:
            self.stats.writes_ok += 1
            if request.answer_ok:
                self._respond(level, request.request_id, None, None)
        else:
            self._respond(
                level, request.request_id, result.code, result.message, result.may_have_executed
            )

    def _respond(
        self,
        level: str,
        request_id: object,
        error: str | None,
        message: str | None,
        may_have_executed: bool = False,
    ) -> None:
        if error is not None:
            self.stats.writes_refused += 1
        topic = write_response_topic(self.settings.prefix, level)
        try:
            payload = write_response_payload(
                request_id, error=error, message=message, may_have_executed=may_have_executed
            )
        except (TypeError, ValueError):  # an id JSON cannot echo (cannot happen from JSON)
            payload = write_response_payload(None, error=error, message=message)
        client = self._client
        if client is not None and self.connected:
            task = asyncio.create_task(self._send_response(client, topic, payload))
            self._writes.add(task)
            task.add_done_callback(self._writes.discard)
        else:
            self._put(Publish(topic, payload, 1, False))

    async def _send_response(self, client: Any, topic: str, payload: bytes) -> None:
        try:
            await client.publish(topic, payload, qos=1)
        except Exception:  # connection went away: the queue delivers it after the reconnect
            self._put(Publish(topic, payload, 1, False))
