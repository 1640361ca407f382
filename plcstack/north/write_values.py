"""The one value grammar for writes from the north side (MQTT JSON, Sparkplug DCMD, OPC UA, web).

Each north-side protocol delivers a written value in its own clothes: JSON numbers (where
``1201.0`` is how JavaScript and many JSON producers send an integer), Sparkplug metrics, OPC UA
variants, form fields. :func:`parse_write_value` turns any of them into the Python value
:meth:`Poller.write_tag <plcstack.poll.engine.Poller.write_tag>` encodes, by the tag's declared
type, so that a value one north side takes is taken by every other one, and a value one refuses
is refused by all with the same code and the same words:

========================  ===============================================================
tag type                  accepted (per value; a tag with ``count > 1`` takes a list of them)
========================  ===============================================================
bool                      ``true``/``false``, ``0``/``1`` (also ``0.0``/``1.0``)
integers, BCD, KF/KH/...  an integer, or a float with no fractional part (``1201.0``)
float32, KG, KT           a number
scaled (``scale = ...``)  a number in engineering units
KY                        two bytes: ``[12, 255]`` or ``"12,255"`` (as KY is read and shown)
KC, ``string:N``          a string
raw                       an integer, or ``true``/``false`` on a bit area
========================  ===============================================================

Ranges (``int8`` and ``300``, BCD and ``10000``, text too long) are checked when the value is
encoded (``write_tag``); that refusal is an :class:`~plcstack.errors.AddressError` as well and
gets :data:`WRONG_TYPE` from :func:`result_code`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Final

from plcstack.errors import AddressError, ConnectFailed, PlcError, PlcErrorResponse
from plcstack.north.face import PollerView
from plcstack.poll.config import TagConfig
from plcstack.poll.plan import encode_tag

__all__ = [
    "NOT_WRITABLE",
    "UNKNOWN_TAG",
    "WRONG_TYPE",
    "WriteValueError",
    "bit_of_word_refusal",
    "classify_write_error",
    "expected_value",
    "parse_write_value",
    "result_code",
    "split_element",
    "write_element",
]

#: result codes (the words MQTT write responses carry in ``error``; the web and Modbus sides map
#: them onto their own statuses)
WRONG_TYPE: Final = "wrong_type"
NOT_WRITABLE: Final = "not_writable"
UNKNOWN_TAG: Final = "unknown_tag"


class WriteValueError(AddressError):
    """A written value the tag cannot take; nothing was sent. ``code`` is the result code
    (:data:`WRONG_TYPE`, :data:`NOT_WRITABLE`) every north side answers with."""

    def __init__(
        self,
        message: str,
        *,
        code: str = WRONG_TYPE,
        plc: str | None = None,
        request: str | None = None,
    ) -> None:
        self.code = code
        super().__init__(message, plc=plc, request=request)


def expected_value(tag: TagConfig) -> str:
    """What one value of ``tag`` must look like, in the words every refusal uses."""
    vtype = tag.type
    if tag.scale is not None:
        return "a number (in engineering units)"
    kind, name = vtype.kind, vtype.name
    if name == "bool":
        return "true or false"
    if name == "ky":
        return 'two bytes 0..255, as [high, low] or "high,low"'
    if kind == "int":
        return f"an integer ({vtype.summary})"
    if kind == "float":
        return "a number"
    if kind == "text":
        return f"a string ({vtype.summary})"
    return "an integer (or true/false on a bit area)"


def _integral(value: object) -> int | None:
    """``value`` as an int if it is an integer or an integral finite float, else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return int(value)
    return None


def _number(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        x = float(value)
    except OverflowError:
        return None
    return x if math.isfinite(x) else None


def _ky(value: object) -> tuple[int, int] | None:
    parts: list[object]
    if isinstance(value, str):
        pieces = value.split(",")
        if len(pieces) != 2:
            return None
        try:
            parts = [int(p.strip()) for p in pieces]
        except ValueError:
            return None
    elif isinstance(value, list | tuple) and len(value) == 2:
        parts = list(value)
    else:
        return None
    high, low = _integral(parts[0]), _integral(parts[1])
    if high is None or low is None or not (0 <= high <= 255 and 0 <= low <= 255):
        return None
    return high, low


def _scalar(tag: TagConfig, value: object) -> object:
    """One value of ``tag`` in the form its type encodes, or raises ValueError."""
    vtype = tag.type
    kind, name = vtype.kind, vtype.name
    if tag.scale is not None or kind == "float":
        x = _number(value)
        if x is None:
            raise ValueError
        return x
    if name == "bool":
        if isinstance(value, bool):
            return value
        n = _integral(value)
        if n not in (0, 1):
            raise ValueError
        return bool(n)
    if name == "ky":
        pair = _ky(value)
        if pair is None:
            raise ValueError
        return pair
    if kind == "text":
        if not isinstance(value, str):
            raise ValueError
        return value
    if kind == "raw" and isinstance(value, bool):
        return value
    n = _integral(value)
    if n is None:
        raise ValueError
    return n


def parse_write_value(tag: TagConfig, value: object, *, plc: str | None = None) -> object:
    """The value to hand to ``write_tag`` for ``value`` written to ``tag`` (a
    :class:`~plcstack.poll.config.TagConfig`) by any north-side client.

    A scalar for ``count = 1``, a list of ``count`` values otherwise. Raises
    :class:`WriteValueError` (code :data:`WRONG_TYPE`) naming the tag, what was sent and what the
    tag takes; nothing is written then.
    """
    request = f"write {tag.name}"
    count = tag.count
    takes = expected_value(tag)
    if count == 1:
        try:
            return _scalar(tag, value)
        except ValueError:
            raise WriteValueError(
                f"tag {tag.name!r} takes {takes}, not {value!r}", plc=plc, request=request
            ) from None
    if not isinstance(value, list | tuple):
        raise WriteValueError(
            f"tag {tag.name!r} has {count} values: send a list of {count}, each {takes};"
            f" not {value!r}",
            plc=plc,
            request=request,
        )
    if len(value) != count:
        raise WriteValueError(
            f"tag {tag.name!r} takes a list of {count} values, got {len(value)}",
            plc=plc,
            request=request,
        )
    out: list[object] = []
    for i, item in enumerate(value):
        try:
            out.append(_scalar(tag, item))
        except ValueError:
            raise WriteValueError(
                f"tag {tag.name!r}: value {i} must be {takes}, not {item!r}",
                plc=plc,
                request=request,
            ) from None
    return out


def bit_of_word_refusal(tag_name: str, address: str, *, plc: str | None = None) -> WriteValueError:
    """The one refusal of a write to a bit-of-a-word tag (code :data:`NOT_WRITABLE`)."""
    return WriteValueError(
        f"tag {tag_name!r} is a bit of a word ({address}) and is read-only: writing one bit of"
        " a word would be a read-modify-write racing the PLC program",
        code=NOT_WRITABLE,
        plc=plc,
        request=f"write {tag_name}",
    )


def result_code(error: PlcError) -> str:
    """The result code of an :class:`AddressError` raised by a write before anything was sent:
    the error's own ``code`` if it has one, else :data:`UNKNOWN_TAG` for a tag that does not
    exist and :data:`WRONG_TYPE` for a value the tag's type cannot hold."""
    if isinstance(error, WriteValueError):
        return error.code
    if "no tag named" in error.message:
        return UNKNOWN_TAG
    if "no PLC named" in error.message:
        return "unknown_plc"
    if "bit of a word" in error.message:
        return NOT_WRITABLE
    return WRONG_TYPE


def classify_write_error(exc: BaseException) -> tuple[str, str, bool]:
    """``(result code, message, may_have_executed)`` of a write that raised ``exc``.

    Refused before sending (:class:`AddressError`): :func:`result_code`, not executed. The PLC
    refused it or could not be connected: ``plc_error``, not executed. Any other failure (a
    timeout, a dropped connection after sending, a bug): ``plc_error``, may have executed.
    """
    if isinstance(exc, AddressError):
        return result_code(exc), str(exc), False
    if isinstance(exc, PlcErrorResponse | ConnectFailed):
        return "plc_error", str(exc), False
    if isinstance(exc, PlcError):
        return "plc_error", str(exc), True
    return "plc_error", f"{type(exc).__name__}: {exc}", True


def split_element(name: str) -> tuple[str, int] | None:
    """``("alarms", 3)`` for the element name ``alarms/3`` (as Sparkplug announces the values
    of a tag with ``count > 1``), else None."""
    base, slash, index = name.rpartition("/")
    if not slash or not base or not index.isdigit() or (len(index) > 1 and index[0] == "0"):
        return None
    return base, int(index)


async def write_element(
    poller: PollerView, plc: str, tag: TagConfig, point_bits: int, index: int, value: object
) -> None:
    """Write element ``index`` of ``tag`` (``count > 1``) alone: the points of that one value,
    at its own address, through the poller's single-flight ``write`` (never a read-modify-write
    of the whole array, which would race the PLC program over the other elements)."""
    request = f"write {tag.name}/{index}"
    if not 0 <= index < tag.count:
        raise WriteValueError(
            f"tag {tag.name!r} has elements 0..{tag.count - 1}, not {index}",
            code=UNKNOWN_TAG,
            plc=plc,
            request=request,
        )
    client = poller.client(plc)
    base, bit = client.split_bit(tag.address)
    if bit is not None:
        raise bit_of_word_refusal(tag.name, tag.address, plc=plc)
    try:
        area, start = client.locate(base, tag.count)
        address = client.address_at(area, start + index * tag.type.points_per_value(point_bits))
    except NotImplementedError:
        raise WriteValueError(
            f"tag {tag.name!r}: this PLC's client cannot address one element; write the whole tag",
            plc=plc,
            request=request,
        ) from None
    element = replace(tag, name=f"{tag.name}/{index}", address=address, count=1)
    item = parse_write_value(element, value, plc=plc)
    order = {p.name: p.order for p in poller.config.plcs}[plc]
    try:
        points = encode_tag(element, [item], point_bits, order, client.byte_order)
    except AddressError as exc:
        raise WriteValueError(
            f"tag {element.name!r}: {exc.message}", plc=plc, request=request
        ) from None
    if all(isinstance(p, bool) for p in points):
        await poller.write(plc, address, [bool(p) for p in points])
    else:
        await poller.write(plc, address, [int(p) for p in points])
