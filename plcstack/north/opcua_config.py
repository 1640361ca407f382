"""Settings of the OPC UA server: endpoint, security policies, users. No asyncua import here.

They live in the ``[opcua]`` table of the poller's TOML file, next to the PLCs they serve::

    [opcua]
    listen = "127.0.0.1:4840"        # the default: loopback only ("0.0.0.0:4840": every address)
    path = "/plcstack"               # the endpoint is opc.tcp://LISTEN/PATH
    namespace = "urn:plcstack"
    security_policies = ["None"]     # or e.g. ["Basic256Sha256_SignAndEncrypt"] with a certificate
    certificate = "server-cert.der"  # needed by every policy but None
    private_key = "server-key.pem"
    trusted_client_certificates = "trusted/"   # only these clients' certificates (DER/PEM)
    anonymous = "read"               # "none" | "read" | "write"
    max_clients = 64                 # connections at once; the next is closed at once
    first_request_timeout = 10       # seconds a connection has to activate a session (0: 30)

    [opcua.users.operator]           # user name / password logins
    password_hash = "pbkdf2_sha256$..."   # plcstack serve opcua --hash-password
    write = true                     # may write tags marked writable = true

Secure by default: the server binds 127.0.0.1 unless ``listen`` names another address,
anonymous sessions may read but not write, tags are read-only unless ``writable = true``, and
passwords are stored only as salted PBKDF2 hashes. A configuration that would send passwords in
plain text to a non-loopback address (users configured, no encrypting policy) is refused.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import ipaddress
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from plcstack.checks import Listen, Table
from plcstack.errors import ConfigError
from plcstack.tomlfile import TomlFile
from plcstack.transports.guard import FIRST_REQUEST_TIMEOUT

__all__ = [
    "DEFAULT_ENDPOINT",
    "SECURITY_POLICIES",
    "OpcUaConfig",
    "UserConfig",
    "check_password",
    "hash_password",
    "load_opcua_config",
    "parse_opcua_config",
]

DEFAULT_ENDPOINT = "opc.tcp://127.0.0.1:4840/plcstack"
DEFAULT_NAMESPACE = "urn:plcstack"
#: OPC UA clients at once: a plant has a few (SCADA, historian, engineering laptops)
DEFAULT_MAX_CLIENTS = 64
#: the policy names asyncua offers (``ua.SecurityPolicyType``); "None" is accepted for NoSecurity
SECURITY_POLICIES = (
    "NoSecurity",
    "Basic128Rsa15_Sign",
    "Basic128Rsa15_SignAndEncrypt",
    "Basic256_Sign",
    "Basic256_SignAndEncrypt",
    "Basic256Sha256_Sign",
    "Basic256Sha256_SignAndEncrypt",
    "Aes128Sha256RsaOaep_Sign",
    "Aes128Sha256RsaOaep_SignAndEncrypt",
    "Aes256Sha256RsaPss_Sign",
    "Aes256Sha256RsaPss_SignAndEncrypt",
)
#: with a certificate and no explicit list: the policies that encrypt and are not deprecated
SECURE_POLICIES = (
    "Basic256Sha256_SignAndEncrypt",
    "Aes128Sha256RsaOaep_SignAndEncrypt",
    "Aes256Sha256RsaPss_SignAndEncrypt",
)
ANONYMOUS_MODES = ("none", "read", "write")
#: PBKDF2 rounds of new hashes. A login checks one hash inside asyncua's synchronous user
#: manager, on the event loop: 15-30 ms here, a pause the pollers can take at each login.
HASH_ITERATIONS = 50_000
_HASH_SCHEME = "pbkdf2_sha256"


@dataclass(frozen=True)
class UserConfig:
    """One user name / password login; ``write`` lets it write tags marked ``writable``."""

    name: str
    password_hash: str = field(repr=False)
    write: bool = False


@dataclass(frozen=True)
class OpcUaConfig:
    """Everything :class:`plcstack.north.opcua.OpcUaServer` needs besides the poller."""

    endpoint: str = DEFAULT_ENDPOINT
    namespace: str = DEFAULT_NAMESPACE
    server_name: str = "plcstack"
    #: None: ("NoSecurity",) without a certificate, SECURE_POLICIES with one
    security_policies: tuple[str, ...] | None = None
    certificate: Path | None = None
    private_key: Path | None = None
    #: a directory of trusted client certificates (or their CAs); None: any client certificate
    trusted_client_certificates: Path | None = None
    anonymous: str = "read"
    users: tuple[UserConfig, ...] = ()
    #: connections at once; asyncua closes the next one at once (its own default is 1000,
    #: enough to take the file descriptors the PLC connections need)
    max_clients: int = DEFAULT_MAX_CLIENTS
    #: seconds a new connection has to activate a session before it is closed (asyncua's
    #: activation watchdog; its own default is 30 s)
    first_request_timeout: float = FIRST_REQUEST_TIMEOUT

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def host(self) -> str:
        return urlsplit(self.endpoint).hostname or ""

    @property
    def port(self) -> int:
        port = urlsplit(self.endpoint).port
        return 4840 if port is None else port

    @property
    def policies(self) -> tuple[str, ...]:
        """The effective security policies (asyncua names)."""
        if self.security_policies is not None:
            return self.security_policies
        return SECURE_POLICIES if self.certificate is not None else ("NoSecurity",)


def _validate(config: OpcUaConfig) -> None:
    try:
        parts = urlsplit(config.endpoint)
        port = parts.port
    except ValueError as exc:
        raise ConfigError(
            f"opcua.endpoint {config.endpoint!r}: {exc}", key="opcua.endpoint"
        ) from None
    if parts.scheme != "opc.tcp" or not parts.hostname:
        raise ConfigError(
            f'opcua.endpoint must look like "opc.tcp://HOST:PORT/PATH", not {config.endpoint!r}',
            key="opcua.endpoint",
        )
    if port is not None and not 0 <= port <= 65535:
        raise ConfigError(f"opcua.endpoint: port {port} is out of range", key="opcua.endpoint")
    clients = config.max_clients
    if isinstance(clients, bool) or not isinstance(clients, int) or not 1 <= clients <= 10_000:
        raise ConfigError(
            f"opcua.max_clients must be 1..10000, not {clients!r}", key="opcua.max_clients"
        )
    first = config.first_request_timeout
    if isinstance(first, bool) or not isinstance(first, int | float) or not 0 < first < 1e9:
        raise ConfigError(
            f"opcua.first_request_timeout must be seconds greater than 0, not {first!r}",
            key="opcua.first_request_timeout",
        )
    if not config.namespace:
        raise ConfigError("opcua.namespace must not be empty", key="opcua.namespace")
    if config.anonymous not in ANONYMOUS_MODES:
        raise ConfigError(
            f"opcua.anonymous must be one of {', '.join(ANONYMOUS_MODES)},"
            f" not {config.anonymous!r}",
            key="opcua.anonymous",
        )
    policies = config.policies
    if not policies:
        raise ConfigError(
            "opcua.security_policies must name at least one policy", key="opcua.security_policies"
        )
    for policy in policies:
        if policy not in SECURITY_POLICIES:
            raise ConfigError(
                f"opcua.security_policies: unknown policy {policy!r} "
                f"(known: None, {', '.join(SECURITY_POLICIES[1:])})",
                key="opcua.security_policies",
            )
    if (config.certificate is None) != (config.private_key is None):
        raise ConfigError("opcua: certificate and private_key go together", key="opcua.certificate")
    needs_certificate = any(p != "NoSecurity" for p in policies)
    if needs_certificate and (config.certificate is None or config.private_key is None):
        raise ConfigError(
            "opcua: security policies other than None need certificate and private_key", key="opcua"
        )
    if config.trusted_client_certificates is not None:
        if not needs_certificate:
            raise ConfigError(
                "opcua: trusted_client_certificates needs a security policy but None",
                key="opcua.trusted_client_certificates",
            )
        if "NoSecurity" in policies:
            raise ConfigError(
                "opcua: trusted_client_certificates with the None policy offered: a client on it "
                "sends no certificate, so the trust list would not apply; drop None",
                key="opcua",
            )
    if config.anonymous == "none" and not config.users:
        raise ConfigError(
            'opcua: anonymous = "none" and no [opcua.users]: nobody could log in', key="opcua"
        )
    names = [u.name for u in config.users]
    if len(set(names)) != len(names):
        raise ConfigError("opcua.users: a user name is used twice", key="opcua.users")
    for user in config.users:
        if not user.name:
            raise ConfigError("opcua.users: a user name must not be empty", key="opcua.users")
        _parse_hash(user.password_hash, user.name)
    encrypting = any(p.endswith("SignAndEncrypt") for p in policies)
    if config.users and not encrypting and not _is_loopback(parts.hostname):
        raise ConfigError(
            f"opcua: users are configured but no SignAndEncrypt policy is offered, so passwords "
            f"would cross the network to {parts.hostname} in plain text; add a certificate and "
            f'e.g. security_policies = ["Basic256Sha256_SignAndEncrypt"]',
            key="opcua",
        )


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# -- passwords --------------------------------------------------------------------------------


def hash_password(password: str, *, iterations: int = HASH_ITERATIONS) -> str:
    """A salted PBKDF2-SHA256 hash to put in ``password_hash`` (the password itself never is)."""
    salt = os.urandom(16)
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return "$".join((_HASH_SCHEME, str(iterations), _b64(salt), _b64(digest)))


def check_password(password: str, password_hash: str) -> bool:
    """Whether ``password`` matches ``password_hash`` (constant-time comparison)."""
    iterations, salt, digest = _parse_hash(password_hash, None)
    candidate = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    return hmac.compare_digest(candidate, digest)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _parse_hash(text: str, user: str | None) -> tuple[int, bytes, bytes]:
    where = f"opcua.users.{user}: " if user else ""
    parts = text.split("$")
    try:
        if len(parts) != 4 or parts[0] != _HASH_SCHEME:
            raise ValueError
        iterations = int(parts[1])
        salt = base64.b64decode(parts[2], validate=True)
        digest = base64.b64decode(parts[3], validate=True)
        if iterations < 1 or not salt or len(digest) != 32:
            raise ValueError
    except ValueError:
        raise ConfigError(
            f"{where}password_hash is not a {_HASH_SCHEME}$ITERATIONS$SALT$HASH string "
            "(make one with: plcstack serve opcua --hash-password)",
            key=f"opcua.users.{user}.password_hash" if user else None,
        ) from None
    return iterations, salt, digest


# -- TOML ---------------------------------------------------------------------------------------

_KEYS = {
    "listen",
    "path",
    "endpoint",
    "namespace",
    "server_name",
    "security_policies",
    "certificate",
    "private_key",
    "trusted_client_certificates",
    "anonymous",
    "users",
    "max_clients",
    "first_request_timeout",
}
#: the face-guard keys other faces take that this one cannot keep, and why (said when a file
#: has them, rather than "unknown key")
_NOT_TAKEN = {
    "max_clients_per_host": "the OPC UA library (asyncua) admits connections without telling"
    " hosts apart and offers no hook to refuse one by its host; max_clients bounds them all",
    "idle_timeout": "the OPC UA library (asyncua) ends an idle session by its session timeout,"
    " which the client asks for and asyncua holds to 5 s..10 minutes; first_request_timeout"
    " bounds a connection that activates no session",
}
DEFAULT_LISTEN = Listen("127.0.0.1", 4840)
DEFAULT_PATH = "/plcstack"


def load_opcua_config(path: str | Path) -> OpcUaConfig:
    """The ``[opcua]`` table of a poller TOML file (defaults if there is none).

    Relative certificate and key paths are taken relative to the file's directory. The whole
    file, every table checked: ``plcstack.load_config(path).north.opcua``.
    """
    file = TomlFile.read(path)
    try:
        return parse_opcua_config(
            Table.of(file.data.get("opcua", {}), "opcua", base=file.base, notices=None)
        )
    except ConfigError as exc:
        raise file.error(exc if exc.key else ConfigError(exc.message, key="opcua")) from None


def parse_opcua_config(section: object, *, base: Path | None = None) -> OpcUaConfig:
    """Build an :class:`OpcUaConfig` from the ``[opcua]`` table's contents."""
    t = Table.of(section, "opcua", base=base)
    for key, why in _NOT_TAKEN.items():
        if key in t:
            raise t.error(key, f"is not taken here: {why}")
    t.keys(_KEYS)
    options: dict[str, Any] = {"endpoint": _endpoint(t)}
    for key in ("namespace", "server_name", "anonymous"):
        if key in t:
            options[key] = _string(t, key)
    if "security_policies" in t:
        raw = t.raw("security_policies")
        if not isinstance(raw, list) or not all(isinstance(p, str) for p in raw):
            raise t.error("security_policies", 'must be a list of names, e.g. ["None"]')
        options["security_policies"] = tuple("NoSecurity" if p == "None" else p for p in raw)
    for key in ("certificate", "private_key", "trusted_client_certificates"):
        if key in t:
            _string(t, key)
            options[key] = Path(t.file(key) or "")
    users = t.sub("users", t.raw("users", {}))
    options["users"] = tuple(_user(users, name, spec) for name, spec in users.values.items())
    if "max_clients" in t:
        options["max_clients"] = t.raw("max_clients")
    if "first_request_timeout" in t:
        # 0: asyncua's own 30 s (its activation watchdog cannot be turned off from here)
        first = t.seconds("first_request_timeout", 0.0, hi=1e9, zero="asyncua's 30 s")
        options["first_request_timeout"] = first or 30.0
    return OpcUaConfig(**options)


def _endpoint(t: Table) -> str:
    """``opc.tcp://LISTEN/PATH`` from ``listen`` and ``path``, or from the old ``endpoint``
    (a notice names the new spelling)."""
    if "endpoint" in t:
        for new in ("listen", "path"):
            if new in t:
                raise t.error(
                    "endpoint", f"and {new} both say where to listen: keep {new}, drop endpoint"
                )
        endpoint = _string(t, "endpoint")
        try:
            parts = urlsplit(endpoint)
            port = parts.port
        except ValueError as exc:
            raise t.error("endpoint", f"{endpoint!r}: {exc}") from None
        if parts.scheme != "opc.tcp" or not parts.hostname:
            raise t.error(
                "endpoint", f'must look like "opc.tcp://HOST:PORT/PATH", not {endpoint!r}'
            )
        listen = Listen(parts.hostname, DEFAULT_LISTEN.port if port is None else port)
        path = parts.path or "/"
        new = f'listen = "{listen}"' + (f' and path = "{path}"' if path != DEFAULT_PATH else "")
        t.notice("endpoint", t.deprecated("endpoint", new))
        return f"opc.tcp://{listen}{path}"
    listen = t.listen(DEFAULT_LISTEN) if "listen" in t else DEFAULT_LISTEN
    path = t.text("path", DEFAULT_PATH)
    if not path.startswith("/") or any(c.isspace() or c in "?#" for c in path):
        raise t.error("path", f'must be a URL path such as "/plcstack", not {path!r}')
    return f"opc.tcp://{listen}{path}"


def _string(t: Table, key: str) -> str:
    value = t.raw(key)
    if not isinstance(value, str):
        raise t.error(key, f"must be a string, not {value!r}")
    return value


def _user(users: Table, name: str, spec: object) -> UserConfig:
    where = f"opcua.users.{name}"
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where} must be a table with password_hash and write", key=where)
    t = users.sub(name, spec)
    hint = "; store a hash: plcstack serve opcua --hash-password" if "password" in t else ""
    t.keys(("password_hash", "write"), hint=hint)
    password_hash = t.raw("password_hash")
    if not isinstance(password_hash, str):
        raise ConfigError(
            f"{where}: missing password_hash (plcstack serve opcua --hash-password)", key=where
        )
    write = t.raw("write", False)
    if not isinstance(write, bool):
        raise t.error("write", f"must be true or false, not {write!r}")
    return UserConfig(name, password_hash, write)
