"""What the command line says over the file (``--web-port``, ``--metrics-port``), applied in
one place.

Every command that runs faces takes the same options with the same meaning, and a reload
applies them again to the file it re-read: a console started with ``--web-port 8081`` stays
on 8081 when the file is edited. An option for a face the file does not configure starts that
face with its defaults (``--web-port`` without ``[web]``: the console on loopback).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from plcstack.config.model import Config
from plcstack.errors import ConfigError
from plcstack.north.metrics import MetricsSettings
from plcstack.north.web.settings import WebSettings

__all__ = ["Overrides", "apply_overrides"]


@dataclass(frozen=True)
class Overrides:
    """The options of one run that replace what the file says (None: the file's)."""

    #: ``--web-port``: the web console's port (0: any free port), host from ``[web] listen``
    web_port: int | None = None
    #: ``--metrics-port``: the port of /metrics and /healthz, host from ``[metrics] listen``
    metrics_port: int | None = None

    def __post_init__(self) -> None:
        for option, port in (("--web-port", self.web_port), ("--metrics-port", self.metrics_port)):
            if port is not None and (
                isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535
            ):
                raise ConfigError(f"{option} must be 0..65535, not {port!r}")


def apply_overrides(config: Config, overrides: Overrides) -> Config:
    """``config`` with what ``overrides`` replaces (the same object when it replaces
    nothing)."""
    north = config.north
    if overrides.web_port is not None:
        web = dataclasses.replace(north.web or WebSettings(), port=overrides.web_port)
        north = dataclasses.replace(north, web=web)
    if overrides.metrics_port is not None:
        metrics = north.metrics or MetricsSettings()
        north = dataclasses.replace(
            north, metrics=dataclasses.replace(metrics, port=overrides.metrics_port)
        )
    if north is config.north:
        return config
    return dataclasses.replace(config, north=north)
