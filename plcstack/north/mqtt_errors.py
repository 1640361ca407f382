"""Why an MQTT connection failed, said as a typed error naming the broker and the meaning.

aiomqtt reports a broker that drops us during the TLS handshake or right after CONNECT (a
missing or untrusted client certificate: with TLS 1.3 the broker's alert arrives only after the
handshake looked complete) as ``MqttError("Operation timed out")``; the reason is only in a log
line of paho (``failed to receive on socket: [SSL: TLSV13_ALERT_CERTIFICATE_REQUIRED] ...``).
:class:`PahoLog` is the logger we give each aiomqtt client: it keeps paho's last error lines for
:func:`connect_error`, which turns the exception plus those lines into a
:class:`~plcstack.errors.ConnectFailed` (never got in) or
:class:`~plcstack.errors.ConnectionLost` (an established session dropped) whose message says
what to change: ``MQTT broker mqtts://broker:8883: connect: the broker requires a client
certificate; set [mqtt] cert_file and key_file (...)``.
"""

from __future__ import annotations

import collections
import logging
from typing import Any, Protocol

from plcstack.errors import ConnectFailed, ConnectionLost, PlcError

__all__ = ["PahoLog", "connect_error", "reason_of"]

log = logging.getLogger("plcstack.north.mqtt")


class PahoLog(logging.Logger):
    """A private logger for one aiomqtt client: remembers paho's warnings and errors (the last
    few, for :func:`connect_error`) and passes them to ``plcstack.north.mqtt`` at DEBUG, so a
    reason that ends up in our own error message is not printed twice."""

    def __init__(self) -> None:
        super().__init__("plcstack.north.mqtt.paho", logging.WARNING)
        self.propagate = False
        self.lines: collections.deque[str] = collections.deque(maxlen=4)
        self.addHandler(_Keep(self))


class _Keep(logging.Handler):
    def __init__(self, owner: PahoLog) -> None:
        super().__init__(logging.WARNING)
        self.owner = owner

    def emit(self, record: logging.LogRecord) -> None:
        try:
            line = record.getMessage()
        except Exception:  # a bad format string in a library must not break the sink
            line = str(record.msg)
        self.owner.lines.append(line)
        log.debug("paho: %s", line)


#: (substring of the TLS/MQTT reason, upper case) -> what it means for the operator
_MEANINGS: tuple[tuple[tuple[str, ...], str], ...] = (
    (
        ("CERTIFICATE_REQUIRED", "PEER DID NOT RETURN A CERTIFICATE"),
        "the broker requires a client certificate",
    ),
    (
        ("UNKNOWN_CA", "BAD_CERTIFICATE", "CERTIFICATE_UNKNOWN", "UNSUPPORTED_CERTIFICATE"),
        "the broker rejected our client certificate (cert_file): not signed by a CA it trusts,"
        " or not meant for client use",
    ),
    (("CERTIFICATE_EXPIRED", "CERTIFICATE HAS EXPIRED"), "a certificate has expired"),
    (
        ("CERTIFICATE_VERIFY_FAILED",),
        "the broker's certificate is not trusted: set [mqtt] ca_file to the CA that signed it",
    ),
    (("WRONG_VERSION_NUMBER",), "the port does not speak TLS (mqtt:// instead of mqtts://?)"),
    (
        ("NOT AUTHORIZED", "BAD USER NAME OR PASSWORD", "BAD_USERNAME_OR_PASSWORD"),
        "the broker refused the login (username_env, password_env)",
    ),
    (("CONNECTION REFUSED", "ERRNO 111"), "nothing listens there (broker down or wrong port)"),
    (
        ("CONNECTION RESET", "ERRNO 104"),
        "the broker closed the connection at once (mqtt:// to a TLS port, mqtts:// to a plain"
        " one, or a broker that refuses this client)",
    ),
)


#: what Python's ssl module says when the peer closes the TLS connection without a close alert
_CLOSED_IN_TLS = "EOF OCCURRED IN VIOLATION OF PROTOCOL"

#: the meaning of a session that was up and then dropped. The meanings above explain a
#: connection the broker would not take (a wrong port, TLS, a login): said of a session that ran,
#: "mqtt:// to a TLS port" sent an operator looking at the configuration after every restart of
#: the broker, whose close arrives as a reset.
_SESSION_MEANINGS: tuple[tuple[tuple[str, ...], str], ...] = (
    (
        ("CONNECTION RESET", "ERRNO 104", "BROKEN PIPE", "ERRNO 32", _CLOSED_IN_TLS),
        "the broker closed the connection (it stopped or restarted, or it dropped this client)",
    ),
)


class ClientCertificate(Protocol):
    """What the diagnosis needs of the ``[mqtt]`` settings: the client certificate, if any."""

    @property
    def cert_file(self) -> str | None: ...


def connect_error(
    exc: BaseException,
    paho_lines: Any,
    *,
    broker: str,
    connected: bool,
    settings: ClientCertificate | None = None,
) -> PlcError:
    """The typed error for a failed connection attempt (``connected`` False) or a dropped
    session (True); ``paho_lines``: what :class:`PahoLog` kept during the attempt."""
    lines = [str(line) for line in paho_lines]
    text = str(exc) or type(exc).__name__
    detail = "; ".join(dict.fromkeys([*lines, text]))
    probe = detail.upper()
    if connected:
        meaning = next((m for keys, m in _SESSION_MEANINGS if any(k in probe for k in keys)), None)
        message = f"{meaning} ({detail})" if meaning else detail
        return ConnectionLost(f"connection lost: {message}", plc=broker, request="session")
    meaning = next((m for keys, m in _MEANINGS if any(k in probe for k in keys)), None)
    cert_file = settings.cert_file if settings is not None else None
    if meaning == _MEANINGS[0][1] and cert_file is None:
        meaning += "; set [mqtt] cert_file and key_file"
    elif meaning == _MEANINGS[0][1]:
        meaning += f"; it did not accept {cert_file!r}"
    if meaning is None and _CLOSED_IN_TLS in probe:
        # The broker hung up during or right after the TLS handshake. Under TLS 1.3 it checks
        # our certificate after the handshake and sends its alert as it closes: whether the
        # alert (UNKNOWN_CA, above) or only the close reaches us is a race. A close is what a
        # rejected certificate looks like when the alert lost that race.
        if cert_file:
            meaning = (
                "the broker closed the TLS connection after the handshake: it most likely "
                f"rejected our client certificate (cert_file {cert_file!r}): not "
                "signed by a CA it trusts, or not meant for client use"
            )
        else:
            meaning = (
                "the broker closed the TLS connection during the handshake; if it requires a "
                "client certificate, set [mqtt] cert_file and key_file"
            )
    message = f"{meaning} ({detail})" if meaning else detail
    return ConnectFailed(message, plc=broker, request="connect")


#: meanings that are one reason for an operator: under TLS 1.3 whether the broker's alert or
#: only its close reaches us is a race, so one missing (or one rejected) client certificate
#: shows as either text from one attempt to the next
_SAME_REASON = (
    (
        (
            "the broker requires a client certificate",
            "the broker closed the TLS connection during the handshake; if it requires a "
            "client certificate",
        ),
        "the broker requires a client certificate",
    ),
    (
        (
            "the broker rejected our client certificate",
            "the broker closed the TLS connection after the handshake: it most likely "
            "rejected our client certificate",
        ),
        "the broker rejected our client certificate",
    ),
)


def reason_of(error: PlcError) -> str:
    """What changes when the reason a broker stays away changes: the sink logs a failed
    attempt once per reason, not once per wording of it (see ``_SAME_REASON``)."""
    message = error.message
    for prefixes, reason in _SAME_REASON:
        if message.startswith(prefixes):
            return reason
    return message
