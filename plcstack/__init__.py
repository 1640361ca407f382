"""plcstack: an asyncio protocol stack for legacy PLCs (MELSEC A-series E71, Siemens S5-LAN-LINK,
AS511 and FETCH/WRITE), with one error model, typed values and a poller for many PLCs.

    import plcstack
    from plcstack.values import INT16, KG, BOOL

    async with plcstack.connect("s5lan://10.0.0.7:5010") as plc:
        words = await plc.read("DB10.DW0", 10)          # list[int]
        level = await plc.read_as("DB10.DW4", KG)       # float (S5 KG real)
        door = await plc.read_as("DB10.DW6.3", BOOL)    # bool (bit 3 of DW6)
        await plc.write_as("DB10.DW8", INT16, -5)       # checked before anything is sent

Blocking, for scripts and notebooks: ``with plcstack.sync.connect(url) as plc: plc.read_as(...)``.

Clients (one per protocol; :func:`connect` picks one from the URL scheme):

* :class:`E71Client` - ``e71+tcp://HOST:PORT``, ``e71+udp://HOST:PORT``
* :class:`S5LanClient` - ``s5lan://HOST:PORT``
* :class:`AS511Client` - ``as511:///dev/ttyS0``, ``as511+tcp://HOST:PORT``
* :class:`FetchWriteClient` - ``fetchwrite://HOST:PORT`` (``?mk=1`` for the Tani header)

Value types (:mod:`plcstack.values`, :class:`ValueType`): ``INT8`` .. ``UINT32``, ``FLOAT32``,
``BCD16``, ``BCD32``, the S5 formats ``KF``, ``KH``, ``KM``, ``KY``, ``KC``, ``KT``, ``KZ``,
``KG``, ``string(n)``, ``BOOL`` (also a bit of a word), ``RAW``.

Many PLCs at once: :class:`Poller` with a :class:`PollConfig` (``load_config("plant.toml").poll``).

Errors: every failure is a :class:`PlcError` (``AddressError``, ``OptionError``,
``ValueEncodeError``, ``ValueDecodeError``, ``PlcErrorResponse``, ``PlcTimeout``,
``ConnectionLost``/``ConnectFailed``, ``RemoteProtocolError``, ``LocalProtocolError``).
"""

from pathlib import Path
from typing import TYPE_CHECKING

from plcstack import sync
from plcstack.clients import (
    AS511Client,
    Client,
    E71Client,
    FetchWriteClient,
    S5LanClient,
    connect,
)
from plcstack.errors import (
    AddressError,
    ConfigError,
    ConnectFailed,
    ConnectionLost,
    LocalProtocolError,
    OptionError,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
    ValueDecodeError,
    ValueEncodeError,
)
from plcstack.poll import PlcConfig, PollConfig, Poller, TagConfig
from plcstack.url import PlcUrl, parse_url

if TYPE_CHECKING:
    from plcstack.config import Config
from plcstack.values import (
    BCD16,
    BCD32,
    BOOL,
    FLOAT32,
    INT8,
    INT16,
    INT32,
    KC,
    KF,
    KG,
    KH,
    KM,
    KT,
    KY,
    KZ,
    RAW,
    UINT8,
    UINT16,
    UINT32,
    Scale,
    ValueType,
    WordOrder,
    string,
    value_type,
)

__version__ = "0.1.0"

__all__ = [
    "BCD16",
    "BCD32",
    "BOOL",
    "FLOAT32",
    "INT8",
    "INT16",
    "INT32",
    "KC",
    "KF",
    "KG",
    "KH",
    "KM",
    "KT",
    "KY",
    "KZ",
    "RAW",
    "UINT8",
    "UINT16",
    "UINT32",
    "AS511Client",
    "AddressError",
    "Client",
    "ConfigError",
    "ConnectFailed",
    "ConnectionLost",
    "E71Client",
    "FetchWriteClient",
    "LocalProtocolError",
    "OptionError",
    "PlcConfig",
    "PlcError",
    "PlcErrorResponse",
    "PlcTimeout",
    "PlcUrl",
    "PollConfig",
    "Poller",
    "RemoteProtocolError",
    "S5LanClient",
    "Scale",
    "TagConfig",
    "ValueDecodeError",
    "ValueEncodeError",
    "ValueType",
    "WordOrder",
    "__version__",
    "connect",
    "load_config",
    "parse_url",
    "string",
    "sync",
    "value_type",
]


def load_config(path: str | Path) -> "Config":
    """Read a configuration file once and check all of it: the poll tables (``config.poll``,
    what :class:`Poller` takes) and every face's table (``config.north.mqtt``, ...), so a typo
    anywhere stops before anything is sent. Errors are :class:`ConfigError` with the file
    and line."""
    from plcstack.config import load_config as load  # the faces' tables on demand

    return load(path)
