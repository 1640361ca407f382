"""Which workers are alive, from the MQTT broker the plant already runs.

Each worker keeps one MQTT connection with a Last Will and publishes its status, retained, on
``<cluster>/workers/<worker>``::

    {"state": "online", "worker": "w1", "incarnation": "w1/4f1c...", "host": "...", "pid": 123}

The Will is the same record with ``"state": "offline"``: when the worker dies (``kill -9``, power
loss, a cut cable) the broker publishes it as soon as it notices (at once for a closed socket,
after 1.5 keepalives for a silent one), so every other worker learns it within seconds, and a
worker that starts later still sees every status because they are retained.

The live set is every worker whose latest status is ``online``. While this worker is offline
from the broker it keeps the last live set it saw: it cannot learn of changes, and dropping its
PLCs would leave them unpolled if only the broker failed (docs/scale-out.md argues why that is
safe with leases).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import aiomqtt

from plcstack.north.mqtt_client import guarded_client
from plcstack.scale.lease import CoordinationError

__all__ = ["Presence", "parse_mqtt_url"]

#: paho's own log lines ("failed to receive on socket") would reach stderr through logging's
#: last-resort handler; the worker reports connection changes itself, once, in plain words
_QUIET = logging.getLogger("plcstack.scale.mqtt")
_QUIET.addHandler(logging.NullHandler())
_QUIET.propagate = False


def parse_mqtt_url(url: str) -> tuple[str, int]:
    """``mqtt://host[:port]`` -> (host, port); the port defaults to 1883."""
    parts = urlsplit(url if "://" in url else f"mqtt://{url}")
    if parts.scheme not in ("mqtt", "tcp") or not parts.hostname:
        raise ValueError(f"MQTT broker URL must look like mqtt://HOST:PORT, not {url!r}")
    return parts.hostname, parts.port or 1883


class Presence:
    """This worker's presence on the broker at ``url`` and its view of the others.

    ``on_change(live)`` is called with the new live set whenever it changes (after the first
    complete view: every retained status and our own, so a starting worker does not briefly
    think it is alone). ``online`` says whether this worker offers to poll; a worker that lost
    its lease server sets it False, so the others take its PLCs over.
    """

    def __init__(
        self,
        url: str,
        *,
        worker: str,
        incarnation: str,
        cluster: str = "plcstack",
        keepalive: int = 5,
        on_change: Callable[[frozenset[str]], None] | None = None,
        on_event: Callable[[str], None] | None = None,
    ) -> None:
        self.url = url
        self.host, self.port = parse_mqtt_url(url)
        self.worker = worker
        self.incarnation = incarnation
        self.cluster = cluster
        self.keepalive = keepalive
        self.on_change = on_change
        self.on_event = on_event
        self.topic = f"{cluster}/workers/{worker}"
        self.online = True
        self.connected = False
        self.synced = False  # a complete view has been seen at least once
        self.messages = 0  # MQTT messages received (for the scale-out figures)
        self._states: dict[str, dict[str, Any]] = {}
        self._live: frozenset[str] = frozenset()
        self._client: aiomqtt.Client | None = None
        self._closing = False
        self._synced = asyncio.Event()

    # -- records ----------------------------------------------------------------------------------
    def _record(self, state: str) -> bytes:
        record = {
            "state": state,
            "worker": self.worker,
            "incarnation": self.incarnation,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "time": round(time.time(), 3),
        }
        return json.dumps(record, separators=(",", ":")).encode()

    @property
    def live(self) -> frozenset[str]:
        return self._live

    def _recompute(self) -> None:
        live = {w for w, r in self._states.items() if r.get("state") == "online"}
        if self.online:
            live.add(self.worker)
        else:
            live.discard(self.worker)
        new = frozenset(live)
        if new != self._live:
            self._live = new
            if self.synced and self.on_change is not None:
                self.on_change(new)

    def _event(self, text: str) -> None:
        if self.on_event is not None:
            self.on_event(text)

    # -- the connection loop ---------------------------------------------------------------------
    async def wait_synced(self) -> None:
        await self._synced.wait()

    async def run(self) -> None:
        """Stay connected (reconnecting with backoff) until cancelled or :meth:`aclose`."""
        delay = 0.2
        while not self._closing:
            try:
                await self._session()
                delay = 0.2
            except aiomqtt.MqttError as exc:
                if self.connected:
                    self._event(f"lost the MQTT broker {self.url}: {exc}; keeping the last view")
                self.connected = False
            self._client = None
            if self._closing:
                return
            await asyncio.sleep(delay)
            delay = min(delay * 2, max(1.0, self.keepalive / 2))

    async def _session(self) -> None:
        will = aiomqtt.Will(self.topic, self._record("offline"), qos=1, retain=True)
        async with guarded_client(aiomqtt)(
            self.host,
            self.port,
            identifier=f"plcstack-{self.incarnation}",
            will=will,
            keepalive=self.keepalive,
            timeout=max(2.0, self.keepalive),
            logger=_QUIET,
        ) as client:
            self._client = client
            self.connected = True
            await client.subscribe(f"{self.cluster}/workers/+", qos=1)
            # Retained statuses arrive before the echo of our own status on this connection:
            # once our own record comes back, the view is complete.
            await self._publish_state()
            async for message in client.messages:
                self.messages += 1
                self._handle(str(message.topic), message.payload)
                if self._closing:
                    return

    async def _publish_state(self) -> None:
        client = self._client
        if client is None:
            return
        state = "online" if self.online else "standby"
        await client.publish(self.topic, self._record(state), qos=1, retain=True)

    def _handle(self, topic: str, payload: Any) -> None:
        worker = topic.rsplit("/", 1)[-1]
        try:
            record = json.loads(payload) if payload else {}
        except (ValueError, TypeError):
            return  # not ours to interpret; a malformed status never crashes the worker
        if not isinstance(record, dict):
            return
        if worker == self.worker:
            if record.get("incarnation") != self.incarnation:
                # A status of an earlier run of this worker (e.g. its Will, published late):
                # say again who we are.
                if self._client is not None and not self._closing:
                    asyncio.get_running_loop().create_task(self._republish())
                return
            if not self.synced:
                self._recompute()  # not reported yet: the view was incomplete until now
                self.synced = True
                self._synced.set()
                if self.on_change is not None:
                    self.on_change(self._live)
            return
        self._states[worker] = record
        self._recompute()

    async def _republish(self) -> None:
        with contextlib.suppress(aiomqtt.MqttError):
            await self._publish_state()

    async def set_online(self, online: bool) -> None:
        """Offer (True) or withdraw (False) this worker; the others see it within one message."""
        if online == self.online:
            return
        self.online = online
        self._recompute()
        with contextlib.suppress(aiomqtt.MqttError):
            await self._publish_state()

    async def aclose(self) -> None:
        """Say ``offline`` (retained) so the others take over now, then disconnect."""
        self._closing = True
        client = self._client
        if client is not None:
            with contextlib.suppress(aiomqtt.MqttError):
                await client.publish(self.topic, self._record("offline"), qos=1, retain=True)


def require_url(url: str) -> None:
    """Raise :class:`CoordinationError` if ``url`` is no MQTT URL (checked before starting)."""
    try:
        parse_mqtt_url(url)
    except ValueError as exc:
        raise CoordinationError(str(exc), plc=url, request="MQTT presence") from None
