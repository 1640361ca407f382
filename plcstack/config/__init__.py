"""The configuration file: one typed model, read once, with one set of checks.

```python
from plcstack.config import load_config

config = load_config("plant.toml")     # every table checked; errors name FILE:LINE
config.poll                            # the PLCs, scan groups and tags (plcstack.Poller)
config.north.mqtt                      # a face's table, typed (None: not configured)
```

``model`` holds :class:`Config` (the tables and where each is read), ``load`` the reading of a
file, ``overrides`` the command line over it, ``diff`` what a reload changes. The checks every
table uses are :mod:`plcstack.checks`.
"""

from plcstack.config.diff import ConfigDiff, diff
from plcstack.config.load import load_config, parse_config, read_config
from plcstack.config.model import TABLES, Config

__all__ = [
    "TABLES",
    "Config",
    "ConfigDiff",
    "diff",
    "load_config",
    "parse_config",
    "read_config",
]
