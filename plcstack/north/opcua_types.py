"""The OPC UA server's maps: plcstack errors to StatusCodes, tag types to built-in DataTypes,
unit symbols to UNECE UnitIds (documented in docs/opcua.md; tests check table and code agree)."""

from __future__ import annotations

from typing import cast

from asyncua import ua
from asyncua.ua.status_codes import StatusCodes as _S

from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    LocalProtocolError,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
    ValueDecodeError,
)
from plcstack.north.write_values import NOT_WRITABLE, result_code
from plcstack.poll.config import TagConfig

__all__ = [
    "INITIAL_STATUS",
    "STATUS_MAP",
    "UNECE_NAMESPACE",
    "read_status",
    "status",
    "unit_id",
    "variant_type",
    "write_status",
]


def status(code: int) -> ua.StatusCode:
    """A StatusCode of ``code``."""
    # asyncua types its integer fields with int subclasses (ua.UInt32 ...); plain ints are what
    # it stores and encodes, so the casts only tell mypy so
    return ua.StatusCode(cast(ua.UInt32, code))


#: plcstack error type -> OPC UA status of a tag's value, most specific first (the first row whose
#: type the error is an instance of wins). Documented in docs/opcua.md.
STATUS_MAP: tuple[tuple[type[PlcError], int, str], ...] = (
    (PlcTimeout, _S.BadTimeout, "no (complete) answer within the deadline"),
    (ConnectFailed, _S.BadNoCommunication, "the PLC cannot be connected (refused, unreachable)"),
    (ConnectionLost, _S.BadCommunicationError, "the connection dropped during the request"),
    (RemoteProtocolError, _S.BadCommunicationError, "the PLC's reply broke the protocol"),
    (PlcErrorResponse, _S.BadDeviceFailure, "the PLC answered with an error code"),
    (ValueDecodeError, _S.BadOutOfRange, "the points are no valid value of the type (BCD > 9)"),
    (AddressError, _S.BadConfigurationError, "address, count or type does not fit the PLC"),
    (LocalProtocolError, _S.BadInternalError, "plcstack misused its own codec (a bug)"),
    (PlcError, _S.BadUnexpectedError, "any other failure"),
)
#: a tag not polled yet
INITIAL_STATUS = _S.BadWaitingForInitialData


def read_status(error_type: type[PlcError] | None) -> int:
    """The StatusCode of a bad sample whose error had this type (see :data:`STATUS_MAP`)."""
    if error_type is not None:
        for kind, code, _ in STATUS_MAP:
            if issubclass(error_type, kind):
                return code
    return _S.BadUnexpectedError


def write_status(error: BaseException) -> int:
    """The StatusCode a refused or failed write returns.

    As for reads, except that an :class:`AddressError` from a write is a value the tag's type
    cannot hold (``write_tag`` checks the value before anything is sent): BadOutOfRange.
    A timeout (BadTimeout) means the write may have been executed.
    """
    if isinstance(error, AddressError):
        # a bit of a word is never written (the refusal every north side gives)
        return _S.BadNotWritable if result_code(error) == NOT_WRITABLE else _S.BadOutOfRange
    if isinstance(error, PlcError):
        return read_status(type(error))
    return _S.BadInternalError


# -- data types ---------------------------------------------------------------------------------

#: tag type name -> OPC UA built-in type (the DataType NodeId has the same number)
_VARIANT_TYPES: dict[str, ua.VariantType] = {
    "bool": ua.VariantType.Boolean,
    "int8": ua.VariantType.SByte,
    "uint8": ua.VariantType.Byte,
    "int16": ua.VariantType.Int16,
    "uint16": ua.VariantType.UInt16,
    "int32": ua.VariantType.Int32,
    "uint32": ua.VariantType.UInt32,
    "float32": ua.VariantType.Float,
    # plcstack.values types beyond the plain integers (by name; strings "string:N" by kind)
    "kf": ua.VariantType.Int16,
    "kh": ua.VariantType.UInt16,
    "km": ua.VariantType.UInt16,
    "kz": ua.VariantType.UInt16,
    "bcd16": ua.VariantType.UInt16,
    "bcd32": ua.VariantType.UInt32,
    "kc": ua.VariantType.String,
    "ky": ua.VariantType.String,  # two bytes, shown as STEP 5 does: "12,255"
    "kt": ua.VariantType.Double,  # seconds
    "kg": ua.VariantType.Double,  # the KG range reaches below float32's normal range
}
#: a ``raw`` tag is one point: a bit, a byte (S5 byte areas) or a word
_RAW_TYPES = {1: ua.VariantType.Boolean, 8: ua.VariantType.Byte, 16: ua.VariantType.UInt16}


def variant_type(tag: TagConfig, point_bits: int) -> ua.VariantType:
    """The OPC UA type of one value of ``tag``; a type without its own mapping is a Double."""
    name = tag.type.name
    if tag.scale is not None:
        return ua.VariantType.Double  # engineering units
    if name == "raw":
        return _RAW_TYPES.get(point_bits, ua.VariantType.UInt32)
    if tag.type.kind == "text":
        return ua.VariantType.String
    return _VARIANT_TYPES.get(name, ua.VariantType.Double)


#: UNECE Recommendation 20 common codes of frequent units (OPC UA Part 8, 5.6.3: UnitId is the
#: code's three characters packed into an Int32); other units get UnitId -1 ("unknown")
_UNECE = {
    "°C": "CEL",
    "degC": "CEL",
    "°F": "FAH",
    "K": "KEL",
    "%": "P1",
    "bar": "BAR",
    "mbar": "MBR",
    "Pa": "PAL",
    "kPa": "KPA",
    "MPa": "MPA",
    "m": "MTR",
    "cm": "CMT",
    "mm": "MMT",
    "m/s": "MTS",
    "A": "AMP",
    "mA": "4K",
    "V": "VLT",
    "W": "WTT",
    "kW": "KWT",
    "Hz": "HTZ",
    "s": "SEC",
    "min": "MIN",
    "h": "HUR",
    "kg": "KGM",
    "t": "TNE",
    "N": "NEW",
    "l": "LTR",
    "rpm": "RPM",
}
UNECE_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"


def unit_id(unit: str) -> int:
    """The OPC UA UnitId of a unit symbol (UNECE common code), -1 if not in the table."""
    code = _UNECE.get(unit)
    if code is None:
        return -1
    value = 0
    for char in code:
        value = (value << 8) | ord(char)
    return value
