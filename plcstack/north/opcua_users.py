"""Who may do what on the OPC UA server: how many clients may connect at once, sessions' logins
(anonymous per ``anonymous``, user names by PBKDF2 password hash), the trust list of client
certificates, and where a session's client is (the write audit's ``peer``)."""

from __future__ import annotations

import logging
import math
import time
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
from plcstack.transports.peer import peer_address

__all__ = [
    "PlcUser",
    "RefusalsOnce",
    "UserManagerOfConfig",
    "limit_clients",
    "session_peer",
    "trust_list",
]

log = logging.getLogger("plcstack.north.opcua")
#: where asyncua says that it refused a connection at its limit
_ASYNCUA_LISTENER = "asyncua.server.binary_server_asyncio"


class RefusalsOnce(logging.Filter):
    """asyncua logs every connection it refuses at its limit as a WARNING: a flood, or a client
    that reconnects in a loop, would be a line per attempt. The first refusal of a burst passes;
    the next ones are counted (``refused``) and dropped until no refusal came for ``quiet``
    seconds. The first line of the next burst says how many the previous one refused after its
    first line."""

    def __init__(self, quiet: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.quiet = quiet
        self.clock = clock
        self.refused = 0
        self._last = -math.inf
        self._unsaid = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if not str(record.msg).startswith("Refusing connection"):
            return True
        self.refused += 1
        now, last = self.clock(), self._last
        self._last = now
        if now - last < self.quiet:
            self._unsaid += 1
            return False
        if self._unsaid:
            record.msg = f"{record.msg} (and {self._unsaid} more refused in the burst before)"
            self._unsaid = 0
        return True


def limit_clients(server: Server, limit: int) -> Callable[[], None]:
    """At most ``limit`` connections to ``server`` at once (asyncua closes the next one at once;
    its own default, 1000, would take the file descriptors the PLC connections need), its
    refusals logged once per burst. Returns what undoes the logging part (at the server's stop).
    """
    server.iserver.max_connections = limit
    refusals = RefusalsOnce()
    listener = logging.getLogger(_ASYNCUA_LISTENER)
    listener.addFilter(refusals)
    return lambda: listener.removeFilter(refusals)


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
