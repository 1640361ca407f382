"""Concurrent polling of many PLCs: configuration, read plans, the Poller and its outputs."""

from plcstack.poll.config import (
    ConfigError,
    PlcConfig,
    PollConfig,
    TagConfig,
    load_config,
    parse_config,
)
from plcstack.poll.engine import PlcStats, Poller, Quality, Sample, format_stats
from plcstack.poll.plan import ReadRequest, ScanPlan, build_plan
from plcstack.poll.values import DataType, WordOrder

__all__ = [
    "ConfigError",
    "DataType",
    "PlcConfig",
    "PlcStats",
    "PollConfig",
    "Poller",
    "Quality",
    "ReadRequest",
    "Sample",
    "ScanPlan",
    "TagConfig",
    "WordOrder",
    "build_plan",
    "format_stats",
    "load_config",
    "parse_config",
]
