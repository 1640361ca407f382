"""Who may do what on the OPC UA server: how many clients may connect at once, sessions' logins
(anonymous per ``anonymous``, user names by PBKDF2 password hash), the trust list of client
certificates, and where a session's client is (the write audit's ``peer``)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.internal_server import InternalServer
from asyncua.server.server import Server
from asyncua.server.user_managers import UserManager

from plcstack.north.opcua_config import OpcUaConfig, check_password
from plcstack.poll.config import ConfigError
from plcstack.transports.guard import FaceGuard
from plcstack.transports.peer import peer_address

__all__ = [
    "AsyncuaSays",
    "PlcUser",
    "UserManagerOfConfig",
    "limit_clients",
    "session_peer",
    "trust_list",
]

log = logging.getLogger("plcstack.north.opcua")
#: where asyncua says what it did with a client's connection
_ASYNCUA_LISTENER = "asyncua.server.binary_server_asyncio"


class AsyncuaSays(logging.Filter):
    """What asyncua's listener logs about its clients, handed to the server's face guard:
    a connection refused at ``max_clients``, one closed because it activated no session in
    time (its activation watchdog: the first request's deadline) and a malformed message header
    are counted by the guard (``plcstack_face_guard_total``) and said once per host per burst
    with their count, instead of one WARNING or ERROR line each (a flood, or a client that
    reconnects in a loop, was a line per attempt)."""

    def __init__(self, guard: FaceGuard) -> None:
        super().__init__()
        self.guard = guard

    def filter(self, record: logging.LogRecord) -> bool:
        text = str(record.msg)
        if text.startswith("Got malformed header"):
            self.guard.malformed(None, None, "a malformed OPC UA message header")
            return False
        if text.startswith("Refusing connection"):
            reason = "max_clients"
        elif text.startswith("Closing idle connection"):
            reason = "first_request_timeout"
        else:
            return True
        peername = record.args[0] if isinstance(record.args, tuple) and record.args else None
        host = str(peername[0]) if isinstance(peername, tuple) and peername else "?"
        peer = peer_address(peername) or host
        self.guard.ended(host, peer, reason, refused=reason == "max_clients")
        return False


def limit_clients(server: Server, guard: FaceGuard) -> Callable[[], None]:
    """The guard's limits on ``server``, as asyncua can keep them: at most ``max_clients``
    connections at once (asyncua closes the next one at once; its own default, 1000, would
    take the file descriptors the PLC connections need), and a session activated within
    ``first_request_timeout``; what it refuses and closes is counted and said by ``guard``
    (:class:`AsyncuaSays`). Returns what undoes the logging part (at the server's stop)."""
    limits = guard.limits
    iserver = server.iserver
    if limits.max_clients is not None:
        iserver.max_connections = limits.max_clients
    if limits.first_request_timeout is not None:
        iserver.max_pending_activation_seconds = limits.first_request_timeout
    says = AsyncuaSays(guard)
    listener = logging.getLogger(_ASYNCUA_LISTENER)
    listener.addFilter(says)
    return lambda: listener.removeFilter(says)


@dataclass
class PlcUser(User):
    """A session's login as this server knows it: asyncua's ``User`` plus the right to write.

    Never ``UserRole.Admin`` (asyncua lets admins skip access-level checks and edit the address
    space); only sessions carrying a PlcUser may write to a PLC.
    """

    may_write: bool = False


class UserManagerOfConfig(UserManager):
    """asyncua user manager: anonymous per ``anonymous``, user names by PBKDF2 password hash."""

    def __init__(self, config: OpcUaConfig) -> None:
        self._anonymous = config.anonymous
        self._users = {u.name: u for u in config.users}

    def get_user(
        self,
        iserver: InternalServer,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> User | None:
        if username is None:
            if self._anonymous == "none":
                return None
            return PlcUser(role=UserRole.User, may_write=self._anonymous == "write")
        user = self._users.get(username)
        if user is None or password is None or not check_password(password, user.password_hash):
            log.warning("OPC UA login refused for user %r", username)
            return None
        return PlcUser(role=UserRole.User, name=username, may_write=user.write)


def session_peer(iserver: InternalServer, user: User) -> str | None:
    """The network address (``host:port``) of the client whose session carries ``user``; None
    for the server's own calls.

    asyncua names each client's session by its connection's peername (``InternalSession.name``,
    set from the transport when the session is created) but hands the attribute service only
    the session's user. :class:`UserManagerOfConfig` makes a new :class:`PlcUser` at every
    activation, so the session is the one whose user *is* this object (asyncua keeps the
    client sessions in ``_external_sessions``; a test of the audit's ``peer`` pins that).
    """
    if not isinstance(user, PlcUser):
        return None
    sessions: dict[Any, Any] = getattr(iserver, "_external_sessions", {})
    for session in list(sessions.values()):
        if session.user is user:
            return peer_address(session.name)
    return None


def _check_directory(directory: Path) -> None:
    if not directory.is_dir():
        raise ConfigError(f"opcua.trusted_client_certificates: {directory} is not a directory")


async def trust_list(directory: Path) -> CertificateValidator:
    """asyncua's validator accepting only client certificates found in (or issued by a CA in)
    ``directory``, also checking validity time, application URI and key usage."""
    _check_directory(directory)  # before asyncua's loader, which would just find nothing
    store = TrustStore([directory], [])
    try:
        await store.load()
    except (OSError, ValueError) as exc:
        raise ConfigError(f"opcua.trusted_client_certificates: {exc}") from None
    options = (
        CertificateValidatorOptions.TRUSTED_VALIDATION | CertificateValidatorOptions.PEER_CLIENT
    )
    return CertificateValidator(options, store)
