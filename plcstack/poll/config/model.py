"""The poller's configuration as typed values: tags, PLCs, scan groups, and their rules.

Built by the TOML loader (:mod:`.loader`, with ``FILE:LINE`` in every error) or in Python; the
same checks run either way (:func:`validate`, called by :class:`PollConfig` itself).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from plcstack.checks import name_problem
from plcstack.errors import AddressError, ConfigError
from plcstack.poll.display import Labels, decimals_problem, labels_problem
from plcstack.url import parse_url
from plcstack.values import (
    RAW,
    ByteOrder,
    Scale,
    ValueType,
    WordOrder,
    default_byte_order,
    default_word_order,
)

__all__ = [
    "DEFAULT_GROUP",
    "MIN_INTERVAL",
    "ConfigError",
    "PlcConfig",
    "PollConfig",
    "TagConfig",
    "batch_wait_problem",
    "text_problem",
    "validate",
]

DEFAULT_GROUP = "default"
DEFAULT_INTERVAL = 1.0
#: shortest scan interval (seconds). A scan is at least one request per PLC; below a millisecond
#: the "interval" only measures how fast a dead PLC can be turned into bad samples (1e-300 gave
#: 15,000 a second of them), never how fast a PLC answers.
MIN_INTERVAL = 0.001
#: no global cap by default: each PLC already has one request in flight at most, and a cap lets
#: a crowd of dead or slow PLCs (each holding a slot for a whole timeout) delay the healthy ones
DEFAULT_CONCURRENCY: int | None = None
DEFAULT_QUEUE = 10_000
#: how long the north side's batch gathers after its first scan (``Poller.scans(wait=)``):
#: with a thousand PLCs a wake-up per loop pass cost the consumer more than the requests did
#: (about 9 us per request); 10 ms is nothing against a historian's or a broker's
#: pace, and each sample keeps its own times
DEFAULT_BATCH_WAIT = 0.01
#: the longest batch_wait taken: more only fills the buffer (and delays every sample)
MAX_BATCH_WAIT = 1.0
DEFAULT_MAX_GAP = 8


@dataclass(frozen=True)
class TagConfig:
    """One tag: ``count`` values of ``type`` starting at ``address``, scanned in ``group``.

    ``address`` may name a bit of a word (``D100.3``, ``DB10.DW5.3``) for ``type`` bool; such a
    tag is read-only (writing one bit of a word would be a read-modify-write that races the PLC).
    ``scale`` maps the raw number linearly onto engineering units (the sample carries a float).
    """

    name: str
    address: str
    type: ValueType[Any] = RAW
    count: int = 1
    group: str = DEFAULT_GROUP
    scale: Scale | None = None
    #: whether north-side servers (OPC UA) may write this tag; the Python API's ``write_tag`` is
    #: not limited by it (the program that owns the poller decides for itself)
    writable: bool = False
    #: engineering unit of the value (``"°C"``, ``"bar"``), for north-side servers (OPC UA
    #: EngineeringUnits); the poller itself does not use it
    unit: str | None = None
    #: what the tag means, for people (``"Feed pump 2 running"``): north-side servers show it
    #: (OPC UA Description, a Sparkplug metric property, the web console); tag lists imported
    #: from engineering tools carry it; the poller itself does not use it
    description: str | None = None
    #: where the Modbus server serves the tag (``"hr:100"``, ``"ir:0"``, ``"co:5"``, ``"di:0"``;
    #: see plcstack.north.modbus); the poller itself does not use it
    modbus: str | None = None
    #: digits after the point when people see the value (plcstack.poll.display)
    decimals: int | None = None
    #: names of the states of a bool or integer tag, ``((0, "stopped"), (1, "running"))``
    labels: Labels | None = None
    #: the tag's line in the TOML file (the errors of the poller and of north-side servers
    #: about it name it); None for tags built in Python
    line: int | None = field(default=None, compare=False)


@dataclass(frozen=True)
class PlcConfig:
    """One PLC: its URL, its tags and how to poll it."""

    name: str
    url: str
    tags: tuple[TagConfig, ...]
    max_gap: int = DEFAULT_MAX_GAP
    word_order: WordOrder | None = None
    timeout: float | None = None
    connect_timeout: float | None = None
    #: cap of the reconnect backoff (None: the client's default, 30 s)
    backoff_max: float | None = None
    #: the line of its ``[[plc]]`` header in the TOML file (None: built in Python)
    line: int | None = field(default=None, compare=False)

    @property
    def order(self) -> WordOrder:
        if self.word_order is not None:
            return self.word_order
        return default_word_order(parse_url(self.url).scheme)

    @property
    def byte_order(self) -> ByteOrder:
        """Order of the characters in a word (text types): the PLC family's."""
        return default_byte_order(parse_url(self.url).scheme)


@dataclass(frozen=True)
class PollConfig:
    """Everything the :class:`~plcstack.poll.engine.Poller` needs."""

    plcs: tuple[PlcConfig, ...]
    groups: Mapping[str, float] = field(default_factory=lambda: {DEFAULT_GROUP: DEFAULT_INTERVAL})
    concurrency: int | None = DEFAULT_CONCURRENCY
    queue: int = DEFAULT_QUEUE
    #: seconds the north side's batches gather (see :data:`DEFAULT_BATCH_WAIT`)
    batch_wait: float = DEFAULT_BATCH_WAIT
    #: the file it was read from (``file:line`` in the north side's errors); None if built in
    #: Python
    source: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        validate(self)


# -- validation shared by TOML and Python-built configs --------------------------------------


def batch_wait_problem(wait: object) -> str | None:
    """What is wrong with a ``batch_wait`` value, or None: the one rule, for the TOML loader
    (which adds the file and line) and for configs built in Python."""
    if (
        isinstance(wait, bool)
        or not isinstance(wait, int | float)
        or not (0 <= wait <= MAX_BATCH_WAIT)
    ):
        return (
            f"poll.batch_wait must be a number of seconds from 0 to {MAX_BATCH_WAIT:g}, "
            f"not {wait!r}"
        )
    return None


#: longest tag description taken: a paragraph, not a manual (OPC UA clients show it in one line)
MAX_DESCRIPTION = 1024


def text_problem(key: str, value: object) -> str | None:
    """What is wrong with a tag's free-text field (``description``), or None: the one rule for
    the TOML loader and for configs built in Python. Control characters other than tab are
    refused so the text prints on one line in logs, CSV and the OPC UA browse tree."""
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        return f"{key} must be a non-empty string, not {value!r}"
    if len(value) > MAX_DESCRIPTION:
        return f"{key} must be at most {MAX_DESCRIPTION} characters, not {len(value)}"
    bad = next((c for c in value if (ord(c) < 32 and c != "\t") or ord(c) == 127), None)
    if bad is not None:
        return f"{key} must not contain control characters (found {bad!r})"
    return None


def validate(config: PollConfig) -> None:
    """Check a config built in Python the same way the TOML loader does."""
    if config.concurrency is not None and config.concurrency < 1:
        raise ConfigError("poll.concurrency must be at least 1")
    if config.queue < 1:
        raise ConfigError("poll.queue must be at least 1")
    problem = batch_wait_problem(config.batch_wait)
    if problem:
        raise ConfigError(problem)
    for name, interval in config.groups.items():
        problem = name_problem("scan group", name)
        if problem:
            raise ConfigError(problem)
        if not (
            isinstance(interval, int | float)
            and math.isfinite(interval)
            and interval >= MIN_INTERVAL
        ):
            raise ConfigError(
                f"scan group {name!r}: interval must be a number of seconds "
                f"of at least {MIN_INTERVAL:g}, not {interval!r}"
            )
    seen: set[str] = set()
    for plc in config.plcs:
        problem = name_problem("PLC", plc.name)
        if problem:
            raise ConfigError(problem, plc=plc.name if isinstance(plc.name, str) else None)
        if plc.name in seen:
            raise ConfigError(f"PLC name {plc.name!r} is used twice", plc=plc.name)
        seen.add(plc.name)
        try:
            parse_url(plc.url)
        except AddressError as exc:
            raise ConfigError(f"bad url: {exc}", plc=plc.name) from None
        if plc.max_gap < 0:
            raise ConfigError("max_gap must be 0 or more", plc=plc.name)
        for name in ("timeout", "connect_timeout", "backoff_max"):
            value = getattr(plc, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be greater than 0", plc=plc.name)
        tag_names: set[str] = set()
        for tag in plc.tags:
            where = f"tag {tag.name!r}"
            problem = name_problem("tag", tag.name)
            if problem:
                raise ConfigError(problem, plc=plc.name)
            if tag.name in tag_names:
                raise ConfigError(f"{where} is defined twice", plc=plc.name)
            tag_names.add(tag.name)
            if tag.count < 1:
                raise ConfigError(f"{where}: count must be at least 1", plc=plc.name)
            if not isinstance(tag.type, ValueType):
                raise ConfigError(f"{where}: type must be a ValueType", plc=plc.name)
            if tag.scale is not None and tag.type.kind not in ("int", "float"):
                raise ConfigError(
                    f"{where}: scale needs a numeric type, not {tag.type.name}", plc=plc.name
                )
            problem = (
                text_problem("description", tag.description)
                or decimals_problem(tag.decimals)
                or labels_problem(tag.labels, tag.type)
            )
            if problem:
                raise ConfigError(f"{where}: {problem}", plc=plc.name)
            if tag.group not in config.groups:
                raise ConfigError(
                    f"{where}: unknown scan group {tag.group!r} "
                    f"(groups: {', '.join(sorted(config.groups))})",
                    plc=plc.name,
                )
