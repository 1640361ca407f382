"""Pieces every Sans-IO codec shares: the event base, the ERROR state, NEED_DATA, a buffer.

Every protocol has the same shape (h11/wsproto style): a ``ClientConnection`` and a
``ServerConnection`` per codec module, ``send(event) -> bytes``, ``receive_data(data)``,
``next_event() -> Event | NEED_DATA``. Events derive from :class:`Event`. A connection whose peer
sent bytes it refused (:class:`RemoteProtocolError`) is in the ERROR state (:class:`ErrorState`)
and refuses further use: it can no longer know where the next message starts.
"""

from __future__ import annotations

import dataclasses
import enum
import struct
import types
from typing import Any, Final, TypeVar

from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = ["NEED_DATA", "ErrorState", "Event", "NeedData", "ReceiveBuffer", "slot_init"]


class Event:
    """Base of every codec event (requests, responses, acks, refusals) of every protocol.

    Events are frozen dataclasses with slots; this base adds no fields, so ``isinstance(x,
    Event)`` tells a protocol event from anything else (e.g. ``NEED_DATA``).
    """

    __slots__ = ()


_E = TypeVar("_E", bound=type)


def slot_init(cls: _E) -> _E:
    """Give a frozen, slotted dataclass an ``__init__`` that stores through the slots' own
    descriptors; the class and its behaviour are otherwise unchanged.

    Why: the generated ``__init__`` of a frozen dataclass calls ``object.__setattr__`` per
    field (the generic attribute protocol, ~40 % of building the object); events such as a
    64-word read and its answer are built once per request on the polling hot path. The
    replacement has the generated one's signature (same parameters, defaults, keyword-only
    fields) and sets the same fields; :func:`dataclasses.replace`, ``__eq__``, ``__hash__``
    and the refusal of later assignment are the dataclass's own. Only for classes without
    ``__post_init__``, default factories or ``init=False`` fields (checked here).
    """
    fields = dataclasses.fields(cls)
    params: list[str] = []
    kw_only: list[str] = []
    lines: list[str] = []
    namespace: dict[str, Any] = {}
    for f in fields:
        if not f.init or f.default_factory is not dataclasses.MISSING:
            raise TypeError(f"slot_init: {cls.__name__}.{f.name} needs the generated __init__")
        descriptor = getattr(cls, f.name, None)
        if not isinstance(descriptor, types.MemberDescriptorType):
            raise TypeError(f"slot_init: {cls.__name__}.{f.name} is not a slot")
        namespace[f"_set_{f.name}"] = descriptor.__set__
        param = f.name
        if f.default is not dataclasses.MISSING:
            namespace[f"_default_{f.name}"] = f.default
            param += f"=_default_{f.name}"
        (kw_only if f.kw_only else params).append(param)
        lines.append(f"    _set_{f.name}(self, {f.name})\n")
    if hasattr(cls, "__post_init__") or not cls.__dict__["__dataclass_params__"].frozen:
        raise TypeError(f"slot_init: {cls.__name__} must be frozen and have no __post_init__")
    signature = ", ".join(["self", *params, *(["*", *kw_only] if kw_only else [])])
    source = f"def __init__({signature}) -> None:\n" + "".join(lines or ["    pass\n"])
    exec(source, namespace)  # the way dataclasses builds the __init__ it replaces
    init = namespace["__init__"]
    init.__annotations__ = dict(cls.__dict__["__init__"].__annotations__)
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    init.__module__ = cls.__module__
    init.__doc__ = "Set every field through its slot (see plcstack.codecs._common.slot_init)."
    GENERATED_INITS[cls] = cls.__dict__["__init__"]
    cls.__init__ = init  # type: ignore[misc]
    return cls


#: class -> the ``__init__`` dataclasses generated, which :func:`slot_init` replaced (tests build
#: objects both ways and compare them)
GENERATED_INITS: Final[dict[type, Any]] = {}


class ErrorState:
    """The ERROR state of h11/wsproto for one connection object.

    A connection records the :class:`RemoteProtocolError` it raised (:meth:`_broken`); from then
    on :meth:`_check_usable` raises :class:`LocalProtocolError` naming that first error, so a
    caller cannot go on decoding a stream whose framing is lost. Make a new connection object
    (the clients do on reconnect).
    """

    #: the RemoteProtocolError that put this connection in the ERROR state, or None
    error: RemoteProtocolError | None = None

    @property
    def errored(self) -> bool:
        """Whether the connection is in the ERROR state."""
        return self.error is not None

    def _check_usable(self) -> None:
        if self.error is not None:
            raise LocalProtocolError(
                f"{type(self).__name__} is in the ERROR state after: {self.error.message}; "
                "use a new connection"
            )

    def _broken(self, exc: RemoteProtocolError) -> RemoteProtocolError:
        """Enter the ERROR state because of ``exc``; returns it for ``raise``."""
        if self.error is None:
            self.error = exc
        return exc


class NeedData(enum.Enum):
    """Returned by ``next_event()`` when more bytes must arrive before an event can be produced.

    An enum member rather than ``object()`` so that type checkers can narrow ``Event | NeedData``.
    """

    NEED_DATA = "NEED_DATA"

    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA: Final = NeedData.NEED_DATA


class ReceiveBuffer:
    """A byte buffer that consumes from the front without copying the tail each time.

    Stream decoders take a frame off the front once they know its length; ``bytearray`` deletion
    from the front is O(n), so we keep a read offset and compact only when it pays. Whenever all
    of it is taken, the bytearray is emptied and the offset goes back to 0, so it is empty
    exactly when nothing is buffered.
    """

    __slots__ = ("_pos", "held")

    def __init__(self) -> None:
        #: the bytearray behind the buffer, one object for the buffer's life; the bytes before
        #: the read offset are taken already. It is empty exactly when nothing is buffered: a
        #: decoder's fast path binds it once and tests it by truth value, no Python call
        #: (``if buffer`` would call ``__bool__``). Read it, never change it.
        self.held = bytearray()
        self._pos = 0

    def __len__(self) -> int:
        return len(self.held) - self._pos

    def __bool__(self) -> bool:
        return bool(self.held)  # emptied whenever everything is taken

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        self.held += data  # nothing to reset: a full take has emptied it already

    def peek(self, n: int | None = None) -> bytes:
        """Up to ``n`` bytes from the front (all if ``None``) without consuming them."""
        end = len(self.held) if n is None else min(len(self.held), self._pos + n)
        return bytes(self.held[self._pos : end])

    def __getitem__(self, index: int) -> int:
        if index < 0 or self._pos + index >= len(self.held):
            raise IndexError(index)
        return self.held[self._pos + index]

    def take(self, n: int) -> bytes:
        """Remove and return exactly ``n`` bytes; the caller has checked ``len(self) >= n``."""
        out = self.take_prefixed(b"", n)  # every prefix starts with b""
        if out is None:
            raise ValueError(f"take({n}) with only {len(self)} bytes buffered")
        return out

    def take_prefixed(self, prefix: bytes, n: int) -> bytes | None:
        """Take exactly ``n`` bytes if that many are buffered and they start with ``prefix``;
        else ``None``, and nothing is taken (a decoder's fast path for a known answer)."""
        buf, pos = self.held, self._pos
        if len(buf) - pos < n or not buf.startswith(prefix, pos):
            return None
        self._pos = end = pos + n
        out = bytes(buf[pos:end])
        if end == len(buf):
            buf.clear()  # all taken: empty, so ``held`` says so
            self._pos = 0
        elif end > 4096 and end * 2 > len(buf):
            del buf[:end]
            self._pos = 0
        return out

    def take_unpacked(self, prefix: bytes, layout: struct.Struct) -> tuple[Any, ...] | None:
        """Take ``prefix`` + ``layout.size`` bytes and return ``layout`` unpacked from the bytes
        after the prefix, if that many are buffered and they start with ``prefix``; else
        ``None``, and nothing is taken. A decoder's fast path for an answer of known size: one
        call, no intermediate ``bytes`` copy of the frame."""
        buf, pos = self.held, self._pos
        have = len(buf)
        start = pos + len(prefix)
        end = start + layout.size
        if have < end or not buf.startswith(prefix, pos):
            return None
        values = layout.unpack_from(buf, start)
        if end == have:
            buf.clear()  # the usual case: the answer was all there was
            self._pos = 0
        else:
            self._pos = end
            if end > 4096 and end * 2 > len(buf):
                del buf[:end]
                self._pos = 0
        return values

    def take_all(self) -> bytes:
        return self.take(len(self))

    def clear(self) -> None:
        self.held.clear()
        self._pos = 0
