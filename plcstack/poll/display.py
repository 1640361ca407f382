"""How people want a tag shown: its ``decimals`` and the ``labels`` of its states.

```toml
[plc.tags]
temp  = { address = "D102", type = "float32", unit = "°C", decimals = 1 }   # 61.5 °C
valve = { address = "M10", type = "bool", labels = ["closed", "open"] }     # false, true
mode  = { address = "D110", type = "int16", labels = { 0 = "stopped", 1 = "running", 7 = "fault" } }
```

``decimals`` (0 to 9) fixes the digits after the point of a number that is not whole (a
``float32``, a ``kg`` or ``kt``, a scaled value). ``labels`` names the states of a ``bool``
(a list of two: false, then true) or of an integer tag (a list for 0, 1, 2, ... or a table of
value = name). The poller ignores both; the web console shows values and draws its charts with
them. Checked here once, for TOML files and for configurations built in Python.
"""

from __future__ import annotations

from typing import Any

from plcstack.values import ValueType

__all__ = ["MAX_DECIMALS", "Labels", "decimals_problem", "labels_problem", "parse_labels"]

MAX_DECIMALS = 9
#: the longest label, in characters (a cell of a table, a tick of a chart)
MAX_LABEL = 40
#: value -> name, in the order written
Labels = tuple[tuple[int, str], ...]


def decimals_problem(value: object) -> str | None:
    """What is wrong with ``decimals``, or None."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_DECIMALS:
        return f"decimals must be a whole number from 0 to {MAX_DECIMALS}, not {value!r}"
    return None


def _label_problem(text: object) -> str | None:
    if not isinstance(text, str) or not text.strip():
        return f"a label must be a non-empty string, not {text!r}"
    if len(text) > MAX_LABEL:
        return f"a label must be at most {MAX_LABEL} characters, not {len(text)} ({text[:20]!r}...)"
    if any(ord(c) < 32 or ord(c) == 127 for c in text):
        return f"a label must not contain control characters ({text!r})"
    return None


def parse_labels(value: Any, dtype: ValueType[Any]) -> Labels:
    """``labels`` as written in TOML (a list, or a table with whole-number keys) as pairs; a
    :class:`ValueError` whose text says what is wrong."""
    pairs: list[tuple[int, str]] = []
    if isinstance(value, list):
        pairs = list(enumerate(value))
    elif isinstance(value, dict):
        for key, text in value.items():
            try:
                number = int(str(key).strip())
            except ValueError:
                raise ValueError(
                    f"labels: {key!r} is not a whole number (a table of value = name)"
                ) from None
            pairs.append((number, text))
    else:
        raise ValueError(
            'labels must be a list ["off", "on"] or a table { 0 = "stopped", 1 = "running" },'
            f" not {value!r}"
        )
    labels = tuple(pairs)
    problem = labels_problem(labels, dtype)
    if problem:
        raise ValueError(problem)
    return labels


def labels_problem(labels: Labels | None, dtype: ValueType[Any]) -> str | None:
    """What is wrong with ``labels`` for a tag of ``dtype``, or None."""
    if labels is None:
        return None
    if dtype.kind not in ("bool", "int", "raw"):
        return f"labels name the states of a bool or an integer tag, not of a {dtype.name}"
    if not labels:
        return "labels must name one state at least"
    if dtype.kind == "bool" and sorted(v for v, _ in labels) != [0, 1]:
        return 'labels of a bool are two: ["when false", "when true"]'
    seen: set[int] = set()
    for number, text in labels:
        if number in seen:
            return f"labels: the value {number} is named twice"
        seen.add(number)
        problem = _label_problem(text)
        if problem:
            return problem
    return None
