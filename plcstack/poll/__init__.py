"""Concurrent polling of many PLCs: configuration, read plans, the Poller and its outputs."""

from plcstack.poll.config import (
    ConfigError,
    PlcConfig,
    PollConfig,
    TagConfig,
    parse_poll_config,
)
from plcstack.poll.engine import PlcStats, Poller, Quality, Sample, Scan, format_stats
from plcstack.poll.plan import ReadRequest, ScanPlan, build_plan
from plcstack.values import Scale, ValueType, WordOrder, value_type

__all__ = [
    "ConfigError",
    "PlcConfig",
    "PlcStats",
    "PollConfig",
    "Poller",
    "Quality",
    "ReadRequest",
    "Sample",
    "Scale",
    "Scan",
    "ScanPlan",
    "TagConfig",
    "ValueType",
    "WordOrder",
    "build_plan",
    "format_stats",
    "parse_poll_config",
    "value_type",
]
