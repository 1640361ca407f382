"""Tag names derived from labels and comments: unique, stable, usable everywhere north.

A device comment is text for people (``"Feed pump 2 running"``, ``"ポンプ運転中"``); a tag name
becomes an MQTT topic level, a Sparkplug metric name, an OPC UA browse name and a TOML key. The
rule, the same for every file:

1. NFKC-normalise (full-width Latin letters and digits become ASCII, half-width katakana
   full-width);
2. keep letters and digits of any script, ``_`` and ``-``; every other run of characters (space,
   punctuation, ``/ + # . :``, control characters) becomes one ``_``;
3. strip ``_`` at both ends and cut to :data:`MAX_NAME` characters;
4. an empty result takes the device's name (``D100``);
5. a name derived for several devices is given to none of them bare: each gets ``_`` and its
   device appended (``pump_running_M10``, ``pump_running_M11``), so a name never depends on the
   order of the rows or on rows added elsewhere;
6. if a name is still taken twice, the file is refused naming both rows.

The result never contains ``/``, ``+``, ``#``, ``.`` or whitespace, so it is one MQTT topic
level, one Sparkplug metric name without folders and one OPC UA browse name.
"""

from __future__ import annotations

import unicodedata
from collections import Counter
from collections.abc import Sequence

from plcstack.tags.table import TagListError

__all__ = ["MAX_NAME", "derive_name", "tag_names"]

#: longest derived name: long enough for a comment's words, short enough for a topic
MAX_NAME = 64


def derive_name(text: str) -> str:
    """Steps 1-3 of the rule: the name ``text`` gives, or ``""`` when nothing is left."""
    out: list[str] = []
    for char in unicodedata.normalize("NFKC", text):
        if char.isalnum() or char in "_-":
            out.append(char)
        elif out and out[-1] != "_":
            out.append("_")
    return "".join(out).strip("_")[:MAX_NAME].rstrip("_")


def tag_names(entries: Sequence[tuple[str, str, int]], source: str) -> list[str]:
    """Names for ``(device, label or comment, line)`` entries, in their order (steps 1-6)."""
    bare = [derive_name(text) or device for device, text, _ in entries]
    used = Counter(bare)
    names = [
        name if used[name] == 1 else f"{name}_{device}"[: MAX_NAME + 1 + len(device)]
        for name, (device, _, _) in zip(bare, entries, strict=True)
    ]
    seen: dict[str, int] = {}
    for name, (device, _, line) in zip(names, entries, strict=True):
        if name in seen:
            raise TagListError.at(
                source,
                line,
                None,
                f"device {device}: derived tag name {name!r} is also the name of row "
                f"{seen[name]}; give one of them a label or a different comment",
            )
        seen[name] = line
    return names
