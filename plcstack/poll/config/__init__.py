"""The poller's configuration: PLCs, scan groups and tags, from TOML or built in Python.

```toml
[poll]
concurrency = 32        # optional cap on requests in flight across all PLCs (default: none;
                        # a scan that finds every slot taken waits its turn in a task)
queue = 10000           # samples held for a slow consumer; beyond that the oldest are dropped
batch_wait = 0.01       # seconds a batch for the north side gathers after its first sample
max_gap = 8             # unused points one merged request may carry between two tags
timeout = 2.0           # request deadline in seconds (a URL's ?timeout= wins)
connect_timeout = 3.0
backoff_max = 30.0      # longest wait between reconnect attempts to a dead PLC (seconds)
interval = 1.0          # interval of the scan group "default" (at least 0.001 s)

[groups]                # more scan groups: name = interval in seconds
fast = 0.1

[[plc]]
name = "press1"
url = "e71+tcp://10.0.0.5:5000"
group = "fast"          # scan group of this PLC's tags unless a tag names one
word_order = "little"   # int32/float32 point order; default: little for E71, big for S5
max_gap = 4

[plc.tags]
counter = "D100"                                          # type raw, count 1
temp = { address = "D102", type = "float32", group = "default" }
alarms = { address = "M0", type = "bool", count = 16 }
level = { address = "D110", type = "int16", scale = [0, 4000, 0.0, 100.0], unit = "%" }
door = { address = "D120.3", type = "bool" }              # bit 3 of D120 (S5: "DB10.DW5.3")
setpoint = { address = "D130", type = "int16", writable = true }   # north-side servers may write
pump = { address = "M10", type = "bool", description = "Feed pump 2 running" }
valve = { address = "M11", type = "bool", labels = ["closed", "open"] }   # shown as the words
mode = { address = "D140", type = "int16", labels = { 0 = "stopped", 1 = "running" } }
flow = { address = "D150", type = "float32", unit = "m³/h", decimals = 1 }
```

Tag types are the value types of :mod:`plcstack.values` by name (``int16``, ``float32``, ``kg``,
``kt``, ``bcd16``, ``string:10``, ...). ``scale = [raw_lo, raw_hi, eng_lo, eng_hi]`` maps a number
linearly onto engineering units (writes map back). ``description`` is free text for people (the
OPC UA Description attribute, a Sparkplug metric property, the web console); the poller ignores it,
as it ignores ``decimals`` and ``labels`` (how the web console shows a value: see
:mod:`plcstack.poll.display`).

The other top-level tables of the same file (``[mqtt]``, ``[opcua]``, ``[web]``, ...) belong to
the layers that use them; :func:`plcstack.config.load_config` reads the file once and hands each
table to its owner. ``model`` holds the typed values and their rules, ``loader`` the TOML.
"""

from plcstack.errors import ConfigError
from plcstack.poll.config.loader import POLL_TABLES, PollTables, parse_poll_config
from plcstack.poll.config.model import (
    DEFAULT_BATCH_WAIT,
    DEFAULT_CONCURRENCY,
    DEFAULT_GROUP,
    DEFAULT_INTERVAL,
    DEFAULT_MAX_GAP,
    DEFAULT_QUEUE,
    MAX_BATCH_WAIT,
    MAX_DESCRIPTION,
    MIN_INTERVAL,
    PlcConfig,
    PollConfig,
    TagConfig,
    batch_wait_problem,
    text_problem,
    validate,
)
from plcstack.tomlfile import toml_line

__all__ = [
    "DEFAULT_BATCH_WAIT",
    "DEFAULT_CONCURRENCY",
    "DEFAULT_GROUP",
    "DEFAULT_INTERVAL",
    "DEFAULT_MAX_GAP",
    "DEFAULT_QUEUE",
    "MAX_BATCH_WAIT",
    "MAX_DESCRIPTION",
    "MIN_INTERVAL",
    "POLL_TABLES",
    "ConfigError",
    "PlcConfig",
    "PollConfig",
    "PollTables",
    "TagConfig",
    "batch_wait_problem",
    "parse_poll_config",
    "text_problem",
    "toml_line",
    "validate",
]
