"""No face or sink of the north side says ``Any`` in its public signature.

A face is typed by :class:`plcstack.north.face.Face`; a constructor or public method that takes
or returns ``Any`` would let an untyped value through that seam unseen by mypy. Every module of
``plcstack.north`` is imported and every class that implements the face protocol (``submit``
and ``health``) is read: the annotations of its constructor and public methods, as written.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re

import plcstack.north

ANY = re.compile(r"\bAny\b")


def _face_classes() -> list[type]:
    found: dict[str, type] = {}
    for info in pkgutil.walk_packages(plcstack.north.__path__, "plcstack.north."):
        try:
            module = importlib.import_module(info.name)
        except ImportError as exc:  # an optional extra (asyncua) not installed
            raise AssertionError(f"{info.name} does not import: {exc}") from exc
        for name, cls in vars(module).items():
            if (
                inspect.isclass(cls)
                and cls.__module__ == module.__name__
                and callable(getattr(cls, "submit", None))
                and callable(getattr(cls, "health", None))
                and not getattr(cls, "_is_protocol", False)
            ):
                found[f"{module.__name__}.{name}"] = cls
    return [found[key] for key in sorted(found)]


def _annotations(cls: type) -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    for name, member in vars(cls).items():
        if name.startswith("_") and name != "__init__":
            continue
        function = member.fget if isinstance(member, property) else member
        if not inspect.isfunction(function):
            continue
        for param, text in function.__annotations__.items():
            out.append((f"{cls.__qualname__}.{name}({param})", str(text)))
    return out


def test_the_faces_are_found() -> None:
    names = {cls.__name__ for cls in _face_classes()}
    assert {"MqttSink", "OpcUaServer", "WebConsole", "MetricsServer", "InfluxSink"} <= names, names


def test_no_any_in_a_face_signature() -> None:
    offenders = [
        f"{where}: {text}"
        for cls in _face_classes()
        for where, text in _annotations(cls)
        if ANY.search(text)
    ]
    assert offenders == [], "\n".join(offenders)
