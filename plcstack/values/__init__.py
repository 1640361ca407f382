"""Value types: how the points a PLC holds become the numbers, texts and bits a user works with.

A client reads *points*: ``bool`` for bit devices, ``int`` for byte or word areas. What those
points mean is not in the protocol: a pair of words may be an IEEE float (MELSEC), an S5 KG real,
two BCD halves or four characters. This module is the one place that knows, used by the clients'
:meth:`~plcstack.clients.base.Client.read_as` / ``write_as``, the poller's tag types and the CLI's
``--type``, so a conversion is written and tested once.

Each type is a :class:`ValueType` object whose type parameter is the Python type of one value, so
mypy sees ``await plc.read_as("DB10.DW4", KG)`` as ``float``. Look a type up by its name with
:func:`value_type` (``"int16"``, ``"kg"``, ``"string:10"``; the names are stable: the poller's
TOML, the CLI and the OPC UA mapping use them).

Order: a value of several points is assembled in the PLC's *word order* (which point holds the
most significant part: MELSEC low word first, S5 high word first) and characters are taken from a
word in its *byte order* (MELSEC low byte first: "12" in D0 is 3231H; S5 high byte first). Clients
carry their family's defaults (``Client.word_order`` / ``byte_order``); both can be overridden.

Every value that cannot be encoded (NaN into KG, 10000 into BCD16, a timer beyond 999 x 10 s) is
refused with :class:`~plcstack.errors.ValueEncodeError` before anything is sent; points that are
not a valid value of the type (a BCD digit above 9) raise
:class:`~plcstack.errors.ValueDecodeError`.

Modules: ``core`` (orders, the :class:`ValueType` protocol), ``types`` (the types and their
names), ``points`` (bit of a word, :class:`Scale`, fast paths of write point lists).
"""

from plcstack.values.core import (
    ByteOrder,
    Endian,
    Point,
    Scalar,
    TagValue,
    ValueType,
    WordOrder,
    default_byte_order,
    default_word_order,
)
from plcstack.values.points import Scale, bits_of_points, pack_ints, plain_words
from plcstack.values.types import (
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
    KT_MAX_SECONDS,
    KY,
    KZ,
    RAW,
    TYPES,
    UINT8,
    UINT16,
    UINT32,
    string,
    value_type,
)

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
    "KT_MAX_SECONDS",
    "KY",
    "KZ",
    "RAW",
    "TYPES",
    "UINT8",
    "UINT16",
    "UINT32",
    "ByteOrder",
    "Endian",
    "Point",
    "Scalar",
    "Scale",
    "TagValue",
    "ValueType",
    "WordOrder",
    "bits_of_points",
    "default_byte_order",
    "default_word_order",
    "pack_ints",
    "plain_words",
    "string",
    "value_type",
]
