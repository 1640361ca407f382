"""Leases with a fencing revision in a NATS JetStream key-value bucket.

One key per exclusive PLC in a bucket whose ``ttl`` (the stream's ``max_age``) is the lease time.
Every operation is a compare-and-set on the key's revision, which JetStream checks on the server:

* acquire = ``create``: succeeds only when the key does not exist (never written, expired, or
  deleted by a release). The revision it returns is the fencing token.
* renew = ``update(last=revision)``: succeeds only while nobody else wrote the key since; each
  renew writes a new message, so the key's age starts again.
* release = ``delete(last=revision)``: the key is free at once for the next owner.

A key nobody renews is removed by the server ``ttl`` after its last write (measured: within about
10 ms with nats-server 2.9.10), so a dead worker's lease frees itself. Safety does not depend on
that timing: the holder stops polling ``guard`` seconds before ``ttl`` has passed since it *sent*
its last successful write (see :class:`Lease`), and the server cannot expire the key earlier than
``ttl`` after it *received* that write.

The value names the worker and this process's incarnation, so a write whose answer was lost
(timeout) can be recognised as our own and adopted instead of waiting for it to expire.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import uuid
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import nats
import nats.errors
import nats.js.errors
from nats.aio.client import Client as NatsClient
from nats.js.api import KeyValueConfig, StorageType
from nats.js.client import JetStreamContext
from nats.js.kv import KeyValue

from plcstack.errors import PlcError
from plcstack.resource import cancel_until_done

__all__ = ["CoordinationError", "Lease", "LeaseStore", "lease_key"]

_T = TypeVar("_T")


def _read_outcome(task: asyncio.Future[Any]) -> None:
    if not task.cancelled():
        task.exception()  # read: never "Task exception was never retrieved"


async def _bounded(request: Awaitable[_T], timeout: float) -> _T:
    """``request`` to NATS, bounded by ``timeout`` as ``asyncio.wait_for`` bounds it, with its
    outcome always read.

    On Python 3.11 ``wait_for`` runs the request in a task of its own. When the worker stops
    (a cancel) just as NATS answers with an error (a ``create`` refused: the key exists), the
    cancel wins and the task's error is left unread, which asyncio reports at garbage
    collection as "Task exception was never retrieved" though nothing went wrong.
    """
    task = asyncio.ensure_future(request)
    task.add_done_callback(_read_outcome)
    return await asyncio.wait_for(task, timeout)


_PLAIN_NAME = re.compile(r"[-_A-Za-z0-9]+")


class CoordinationError(PlcError):
    """A coordination server (MQTT broker, NATS) failed or refused a request; the message names
    the server and what was asked."""


def lease_key(plc: str) -> str:
    """The KV key of a PLC's lease: ``plc.<name>``, or ``plc.=<hex of UTF-8>`` for names with
    characters a key may not hold (``=`` never appears in a plain name, so the two cannot
    collide)."""
    if _PLAIN_NAME.fullmatch(plc):
        return f"plc.{plc}"
    return "plc.=" + plc.encode().hex()


@dataclass(slots=True)
class Lease:
    """A lease held by this process.

    ``fence_at`` (event-loop time) is when polling must have stopped unless a renew succeeds
    first: the send time of the last successful write plus ``ttl - guard``.
    """

    plc: str
    key: str
    revision: int
    fence_at: float


class LeaseStore:
    """The leases of one worker incarnation in bucket ``bucket`` of the NATS server at ``url``.

    Each operation is bounded by ``op_timeout`` (a NATS request that gets no answer counts as
    failed, and the lease may or may not have been written: see :meth:`acquire`).
    """

    def __init__(
        self,
        url: str,
        *,
        worker: str,
        ttl: float,
        guard: float | None = None,
        bucket: str = "plcstack-leases",
        op_timeout: float | None = None,
        connect_timeout: float = 5.0,
        on_connection: Callable[[bool], None] | None = None,
    ) -> None:
        if not ttl > 0:
            raise ValueError("lease ttl must be greater than 0")
        self.url = url
        self.worker = worker
        self.incarnation = f"{worker}/{uuid.uuid4().hex[:12]}"
        self.ttl = float(ttl)
        self.guard = self.ttl / 4 if guard is None else guard
        if not 0 < self.guard < self.ttl:
            raise ValueError("lease guard must be between 0 and the ttl")
        self.bucket = bucket
        self.op_timeout = self.ttl / 4 if op_timeout is None else op_timeout
        self.connect_timeout = connect_timeout
        self.on_connection = on_connection
        self._nc: NatsClient | None = None
        self._kv: KeyValue | None = None
        self._js: JetStreamContext | None = None
        #: keys this incarnation may have written without seeing the answer (timeouts)
        self._maybe_ours: set[str] = set()
        #: key-value requests sent (for the scale-out figures)
        self.ops = 0

    @property
    def connected(self) -> bool:
        return self._nc is not None and self._nc.is_connected and self._kv is not None

    # -- connection -----------------------------------------------------------------------------
    async def connect(self) -> None:
        """Connect and open (or create) the bucket; :class:`CoordinationError` if that fails.

        An existing bucket with another ttl is refused: the fencing rule assumes every worker
        uses the bucket's own ttl.
        """

        async def disconnected() -> None:
            if self.on_connection is not None:
                self.on_connection(False)

        async def reconnected() -> None:
            if self.on_connection is not None:
                self.on_connection(True)

        async def error(exc: Exception) -> None:
            pass  # reconnects are reported through disconnected/reconnected

        try:
            # bounded here: with unlimited reconnects, nats-py retries a first connect forever
            self._nc = await _bounded(
                nats.connect(
                    self.url,
                    name=f"plcstack {self.incarnation}",
                    connect_timeout=max(1, round(self.op_timeout * 4)),
                    reconnect_time_wait=min(1.0, self.ttl / 4),
                    max_reconnect_attempts=-1,
                    ping_interval=max(1, round(self.ttl / 2)),
                    max_outstanding_pings=2,
                    disconnected_cb=disconnected,
                    reconnected_cb=reconnected,
                    error_cb=error,
                ),
                self.connect_timeout,
            )
        except Exception as exc:
            raise CoordinationError(
                f"cannot connect within {self.connect_timeout:g} s: {type(exc).__name__} {exc}",
                plc=self.url,
                request="connect to NATS",
            ) from exc
        js = self._nc.jetstream(timeout=self.op_timeout)
        request = f"open lease bucket {self.bucket!r}"
        try:
            try:
                kv = await js.key_value(self.bucket)
            except nats.js.errors.BucketNotFoundError:
                config = KeyValueConfig(
                    bucket=self.bucket,
                    history=1,
                    ttl=self.ttl,
                    storage=StorageType.FILE,
                    description="plcstack PLC leases (docs/scale-out.md)",
                )
                try:
                    kv = await js.create_key_value(config)
                except nats.js.errors.APIError:
                    kv = await js.key_value(self.bucket)  # another worker created it first
            status = await kv.status()
        except Exception as exc:
            await self.close()
            raise CoordinationError(
                f"{type(exc).__name__}: {exc} (is JetStream enabled: nats-server -js?)",
                plc=self.url,
                request=request,
            ) from exc
        if status.ttl is None or abs(status.ttl - self.ttl) > 1e-3:
            await self.close()
            raise CoordinationError(
                f"the bucket exists with ttl {status.ttl} s, this worker was given {self.ttl} s; "
                "every worker must use the same --lease-ttl (or delete the bucket)",
                plc=self.url,
                request=request,
            )
        self._kv, self._js = kv, js

    async def close(self) -> None:
        """Disconnect; returns once nats-py's own tasks have ended.

        nats-py's close cancels its reconnecting task once and waits for it only briefly; on
        Python 3.11 that task can drop the cancel (a ``wait_for`` inside it) and go on
        reconnecting after the store is closed, a task nobody awaits. So it is cancelled until
        it has ended (:func:`cancel_until_done`).
        """
        nc, self._nc, self._kv, self._js = self._nc, None, None, None
        if nc is None:
            return
        with contextlib.suppress(Exception):
            await nc.close()
        reconnecting = getattr(nc, "_reconnection_task", None)
        if isinstance(reconnecting, asyncio.Task):
            await cancel_until_done([reconnecting])
            await asyncio.gather(reconnecting, return_exceptions=True)

    # -- lease operations -------------------------------------------------------------------------
    def _value(self, plc: str) -> bytes:
        record = {"owner": self.worker, "incarnation": self.incarnation, "plc": plc}
        return json.dumps(record, separators=(",", ":")).encode()

    def _fence_at(self, sent: float) -> float:
        return sent + self.ttl - self.guard

    async def acquire(self, plc: str) -> Lease | None:
        """Take the lease of ``plc``; None while another holds it or NATS does not answer.

        A key left by this incarnation (a write whose answer timed out) is adopted with a
        compare-and-set renew instead of waiting for it to expire.
        """
        kv = self._kv
        if kv is None:
            return None
        key = lease_key(plc)
        loop = asyncio.get_running_loop()
        sent = loop.time()
        self.ops += 1
        try:
            revision = await _bounded(kv.create(key, self._value(plc)), self.op_timeout)
        except nats.js.errors.KeyWrongLastSequenceError:
            if key in self._maybe_ours:
                return await self._adopt(plc, key)
            return None
        except (TimeoutError, nats.errors.Error):
            self._maybe_ours.add(key)
            return None
        self._maybe_ours.discard(key)
        return Lease(plc, key, revision, self._fence_at(sent))

    async def _adopt(self, plc: str, key: str) -> Lease | None:
        kv = self._kv
        if kv is None:
            return None
        self.ops += 1
        try:
            entry = await _bounded(kv.get(key), self.op_timeout)
        except nats.js.errors.KeyNotFoundError:
            self._maybe_ours.discard(key)
            return None  # gone meanwhile: the next acquire creates it
        except (TimeoutError, nats.errors.Error):
            return None
        try:
            record = json.loads(entry.value or b"")
        except ValueError:
            record = {}
        if (
            not isinstance(record, dict)
            or record.get("incarnation") != self.incarnation
            or entry.revision is None
        ):
            self._maybe_ours.discard(key)
            return None
        lease = Lease(plc, key, entry.revision, 0.0)
        return lease if await self.renew(lease) else None

    async def renew(self, lease: Lease) -> bool | None:
        """Renew ``lease`` in place: True renewed (``fence_at`` moved on), False lost (someone
        else wrote the key, or it expired and was taken), None no answer (still held until
        ``fence_at`` unless the write arrived late; the next renew finds out)."""
        kv = self._kv
        if kv is None:
            return None
        sent = asyncio.get_running_loop().time()
        self.ops += 1
        try:
            revision = await _bounded(
                kv.update(lease.key, self._value(lease.plc), last=lease.revision),
                self.op_timeout,
            )
        except nats.js.errors.KeyWrongLastSequenceError:
            if lease.key in self._maybe_ours:
                self._maybe_ours.discard(lease.key)
                adopted = await self._adopt_revision(lease)
                if adopted:
                    return True
            return False
        except (TimeoutError, nats.errors.Error):
            self._maybe_ours.add(lease.key)
            return None
        lease.revision = revision
        lease.fence_at = self._fence_at(sent)
        return True

    async def _adopt_revision(self, lease: Lease) -> bool:
        """A renew whose answer was lost may have been written: if the key holds our incarnation
        under a newer revision, renew from that one."""
        kv = self._kv
        if kv is None:
            return False
        try:
            entry = await _bounded(kv.get(lease.key), self.op_timeout)
            record = json.loads(entry.value or b"")
        except (TimeoutError, ValueError, nats.errors.Error):
            return False
        if (
            not isinstance(record, dict)
            or record.get("incarnation") != self.incarnation
            or entry.revision is None
        ):
            return False
        lease.revision = entry.revision
        return bool(await self.renew(lease))

    async def release(self, lease: Lease) -> bool:
        """Free the lease at once (compare-and-set: never deletes another owner's lease).

        Call it only after polling has stopped. False when it could not be released (then it
        expires ``ttl`` after its last renew).
        """
        kv = self._kv
        if kv is None:
            return False
        self.ops += 1
        try:
            await _bounded(kv.delete(lease.key, last=lease.revision), self.op_timeout)
        except nats.js.errors.APIError:
            self._maybe_ours.discard(lease.key)
            return False  # no longer ours: nothing to release
        except (TimeoutError, nats.errors.Error):
            # no answer: it may still be ours; a later acquire can adopt it
            self._maybe_ours.add(lease.key)
            return False
        self._maybe_ours.discard(lease.key)
        return True

    async def holders(self) -> dict[str, str]:
        """``{key: owner}`` of every lease now in the bucket (for tests and diagnostics).

        The keys come from the bucket's stream (its subjects that hold a message), not from
        nats-py's ``keys()``: that watches the bucket and may end before the first entry
        arrives (it decides "nothing pending" from a consumer just created), returning no keys
        while leases are held.
        """
        kv, js = self._kv, self._js
        if kv is None or js is None:
            return {}
        prefix = f"$KV.{self.bucket}."
        info = await js.stream_info(f"KV_{self.bucket}", subjects_filter=f"{prefix}>")
        out: dict[str, str] = {}
        for subject in sorted(info.state.subjects or {}):
            key = subject[len(prefix) :]
            try:
                entry = await kv.get(key)
            except nats.js.errors.KeyNotFoundError:  # deleted or expired: no holder
                continue
            with contextlib.suppress(ValueError, AttributeError):
                out[key] = str(json.loads(entry.value or b"").get("owner"))
        return out
