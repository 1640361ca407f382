"""The Sparkplug B payload schema, built in Python from the public specification.

Written from the Eclipse Sparkplug 3.0 specification's description of the payload (chapter
"Sparkplug B payload definition": field names, numbers and types of ``Payload`` and ``Metric``),
not from any shipped ``.proto`` file. Only the parts plcstack produces and reads are declared:

``Payload``: ``timestamp`` (1, uint64, ms since the epoch), ``metrics`` (2, repeated Metric),
``seq`` (3, uint64, 0..255), ``uuid`` (4, string), ``body`` (5, bytes).

``Metric``: ``name`` (1), ``alias`` (2, uint64), ``timestamp`` (3, uint64), ``datatype`` (4,
uint32), ``is_historical`` (5), ``is_transient`` (6), ``is_null`` (7) and the value as a oneof:
``int_value`` (10, uint32), ``long_value`` (11, uint64), ``float_value`` (12), ``double_value``
(13), ``boolean_value`` (14), ``string_value`` (15), ``bytes_value`` (16).

``properties`` (9, PropertySet): ``keys`` (1, repeated string) and ``values`` (2, repeated
PropertyValue: ``type`` (1, uint32), ``is_null`` (2), ``int_value`` (3, uint32), ``long_value`` (4,
uint64), ``float_value`` (5), ``double_value`` (6), ``boolean_value`` (7), ``string_value`` (8)).

Metadata (8), data sets, templates and extensions (17-19) are left out; a payload
from another node that carries them still parses (protobuf keeps unknown fields). proto2 syntax,
as in the specification, so ``HasField`` works for every optional field.

Data type codes (Sparkplug 3.0, section "Data types")::

    Int8 1, Int16 2, Int32 3, Int64 4, UInt8 5, UInt16 6, UInt32 7, UInt64 8,
    Float 9, Double 10, Boolean 11, String 12, DateTime 13, Text 14
"""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

__all__ = ["DATATYPES", "Metric", "Payload"]

DATATYPES = {
    "Int8": 1,
    "Int16": 2,
    "Int32": 3,
    "Int64": 4,
    "UInt8": 5,
    "UInt16": 6,
    "UInt32": 7,
    "UInt64": 8,
    "Float": 9,
    "Double": 10,
    "Boolean": 11,
    "String": 12,
    "DateTime": 13,
    "Text": 14,
}

_F = descriptor_pb2.FieldDescriptorProto
_OPTIONAL, _REPEATED = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED


def _field(
    message: Any,
    name: str,
    number: int,
    kind: int,
    *,
    label: int = _OPTIONAL,
    type_name: str | None = None,
    oneof: int | None = None,
) -> None:
    f = message.field.add()
    f.name, f.number, f.type, f.label = name, number, kind, label
    if type_name is not None:
        f.type_name = type_name
    if oneof is not None:
        f.oneof_index = oneof


def _file() -> descriptor_pb2.FileDescriptorProto:
    fd = descriptor_pb2.FileDescriptorProto()
    # our own package name: this is plcstack's declaration of the wire format, not Tahu's file
    fd.name = "plcstack/sparkplug_b.proto"
    fd.package = "plcstack.sparkplug_b"
    fd.syntax = "proto2"
    payload = fd.message_type.add()
    payload.name = "Payload"
    metric = payload.nested_type.add()
    metric.name = "Metric"
    pvalue = payload.nested_type.add()
    pvalue.name = "PropertyValue"
    _field(pvalue, "type", 1, _F.TYPE_UINT32)
    _field(pvalue, "is_null", 2, _F.TYPE_BOOL)
    pvalue.oneof_decl.add().name = "value"
    for name, number, kind in [
        ("int_value", 3, _F.TYPE_UINT32),
        ("long_value", 4, _F.TYPE_UINT64),
        ("float_value", 5, _F.TYPE_FLOAT),
        ("double_value", 6, _F.TYPE_DOUBLE),
        ("boolean_value", 7, _F.TYPE_BOOL),
        ("string_value", 8, _F.TYPE_STRING),
    ]:
        _field(pvalue, name, number, kind, oneof=0)
    pset = payload.nested_type.add()
    pset.name = "PropertySet"
    _field(pset, "keys", 1, _F.TYPE_STRING, label=_REPEATED)
    _field(
        pset,
        "values",
        2,
        _F.TYPE_MESSAGE,
        label=_REPEATED,
        type_name=".plcstack.sparkplug_b.Payload.PropertyValue",
    )
    _field(payload, "timestamp", 1, _F.TYPE_UINT64)
    _field(
        payload,
        "metrics",
        2,
        _F.TYPE_MESSAGE,
        label=_REPEATED,
        type_name=".plcstack.sparkplug_b.Payload.Metric",
    )
    _field(payload, "seq", 3, _F.TYPE_UINT64)
    _field(payload, "uuid", 4, _F.TYPE_STRING)
    _field(payload, "body", 5, _F.TYPE_BYTES)
    extensions = payload.extension_range.add()
    extensions.start, extensions.end = 6, 536870912
    _field(metric, "name", 1, _F.TYPE_STRING)
    _field(metric, "alias", 2, _F.TYPE_UINT64)
    _field(metric, "timestamp", 3, _F.TYPE_UINT64)
    _field(metric, "datatype", 4, _F.TYPE_UINT32)
    _field(metric, "is_historical", 5, _F.TYPE_BOOL)
    _field(metric, "is_transient", 6, _F.TYPE_BOOL)
    _field(metric, "is_null", 7, _F.TYPE_BOOL)
    props = ".plcstack.sparkplug_b.Payload.PropertySet"
    _field(metric, "properties", 9, _F.TYPE_MESSAGE, type_name=props)
    metric.oneof_decl.add().name = "value"
    for name, number, kind in [
        ("int_value", 10, _F.TYPE_UINT32),
        ("long_value", 11, _F.TYPE_UINT64),
        ("float_value", 12, _F.TYPE_FLOAT),
        ("double_value", 13, _F.TYPE_DOUBLE),
        ("boolean_value", 14, _F.TYPE_BOOL),
        ("string_value", 15, _F.TYPE_STRING),
        ("bytes_value", 16, _F.TYPE_BYTES),
    ]:
        _field(metric, name, number, kind, oneof=0)
    return fd


_pool = descriptor_pool.DescriptorPool()
_pool.Add(_file())
#: the Payload message class (``Payload()``, ``.SerializeToString()``, ``.FromString(b)``)
Payload: Any = message_factory.GetMessageClass(
    _pool.FindMessageTypeByName("plcstack.sparkplug_b.Payload")
)
#: the nested Metric message class
Metric: Any = message_factory.GetMessageClass(
    _pool.FindMessageTypeByName("plcstack.sparkplug_b.Payload.Metric")
)
