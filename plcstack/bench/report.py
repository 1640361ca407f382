"""Output of a run: a table on stdout, ``--json FILE`` and ``--plot FILE.png``.

JSON schema: ``{"results": [{"case", "loop", "n", "ops_per_s", "floor_ops_per_s",
"ratio", "p99_ms", ...extras}], "meta": {...}}``. ``ops_per_s`` is the median over repeats; a
skipped case has ``null`` numbers and says why in ``note``. Codec rows are per operation
(``us_per_op``; ``ops_per_s`` = 1e6 / us_per_op) with ``loop`` = ``"-"``.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from plcstack.bench.png import PALETTE, RGB, ChartSeries, line_chart
from plcstack.bench.runner import Result

__all__ = ["chart_series", "format_table", "write_json", "write_plot"]


#: notes longer than this are cut in the table (the JSON file keeps them whole)
NOTE_WIDTH = 90


def _num(value: float | None, digits: int = 0) -> str:
    if value is None:
        return "-"
    if digits == 0:
        return f"{value:,.0f}"
    return f"{value:.{digits}f}"


def format_table(results: Sequence[Result]) -> str:
    """A fixed-width table; skipped cases keep their row with the reason."""
    headers = [
        "case",
        "loop",
        "N",
        "stack ops/s",
        "min..max",
        "floor ops/s",
        "ratio",
        "p50 ms",
        "p99 ms",
        "KiB/conn s|f",
        "note",
    ]
    rows: list[list[str]] = []
    for r in results:
        note = r.note if len(r.note) <= NOTE_WIDTH else r.note[: NOTE_WIDTH - 3] + "..."
        if not r.ran:
            rows.append([r.case, r.loop, str(r.n), "skipped", "", "", "", "", "", "", note])
            continue
        if r.us_per_op is not None:
            spread = f"{_num(r.us_per_op, 2)} us/op"
            floor = f"{_num(r.floor_ops_per_s)}" if r.floor_ops_per_s else "-"
            if r.floor_us_per_op is not None:
                floor += f" ({_num(r.floor_us_per_op, 2)} us)"
        else:
            spread = f"{_num(r.ops_min)}..{_num(r.ops_max)}"
            floor = _num(r.floor_ops_per_s)
        rss = ""
        if r.rss_kib_per_conn is not None or r.floor_rss_kib_per_conn is not None:
            rss = f"{_num(r.rss_kib_per_conn, 1)}|{_num(r.floor_rss_kib_per_conn, 1)}"
        rows.append(
            [
                r.case,
                r.loop,
                str(r.n),
                _num(r.ops_per_s),
                spread,
                floor,
                _num(r.ratio, 2),
                _num(r.p50_ms, 3),
                _num(r.p99_ms, 3),
                rss,
                r.note,
            ]
        )
    widths = [
        max(len(h), *(len(row[i]) for row in rows)) if rows else len(h)
        for i, h in enumerate(headers)
    ]
    numeric = {2, 3, 5, 6, 7, 8}

    def fmt(cells: list[str]) -> str:
        out = []
        for i, cell in enumerate(cells):
            out.append(cell.rjust(widths[i]) if i in numeric else cell.ljust(widths[i]))
        return "  ".join(out).rstrip()

    lines = [fmt(headers), fmt(["-" * w for w in widths])]
    lines += [fmt(row) for row in rows]
    return "\n".join(lines)


def meta() -> dict[str, Any]:
    return {
        "python": sys.version.split()[0],
        "implementation": platform.python_implementation(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
    }


def write_json(path: str | Path, results: Sequence[Result], extra: dict[str, Any]) -> None:
    document = {"results": [r.to_json() for r in results], "meta": {**meta(), **extra}}
    Path(path).write_text(json.dumps(document, indent=2) + "\n", encoding="utf-8")


#: line style per kind of measurement: the colour says which protocol (and loop)
KIND_DASH = {"poll": 0, "clients": 3, "stack": 0, "floor": 8, "hsl-threads": 14}


def chart_series(results: Sequence[Result]) -> list[ChartSeries]:
    """ops/s against N: one line per (protocol, loop, kind); colour = protocol and loop,
    line style = kind (poll solid, clients dotted, floor dashed, peers long dashes).

    The one-connection read row of the same protocol is the N = 1 point of each fan-out line.
    """
    lines: dict[str, ChartSeries] = {}
    colours: dict[str, RGB] = {}

    def add(protocol: str, loop: str, kind: str, n: int, rate: float) -> None:
        suffix = "" if loop in ("asyncio", "threads") else f" {loop}"
        key = f"{protocol} {kind}{suffix}"
        colour = colours.setdefault(f"{protocol}{suffix}", PALETTE[len(colours) % len(PALETTE)])
        series = lines.setdefault(key, ChartSeries(key, [], KIND_DASH.get(kind, 0), colour))
        if all(point_n != n for point_n, _ in series.points):
            series.points.append((n, rate))

    for r in results:
        if not r.ran or r.group not in ("conn", "fanout", "peer") or r.ops_per_s is None:
            continue
        parts = r.case.split("/")
        protocol = parts[1]
        if r.group == "conn":
            if not parts[-1].startswith("read"):
                continue
            kinds = ["clients", "poll"]
        else:
            kinds = [parts[2]]
        for kind in kinds:
            add(protocol, r.loop, kind, r.n, r.ops_per_s)
        if r.floor_ops_per_s and r.group != "peer":
            add(protocol, r.loop, "floor", r.n, r.floor_ops_per_s)
    # a line with only its N = 1 point (no fan-out of that kind ran) says nothing
    return [s for s in lines.values() if len(s.points) > 1]


def write_plot(path: str | Path, results: Sequence[Result], title: str) -> int:
    """Write the PNG; returns the number of lines drawn (0: an empty chart with axes)."""
    series = chart_series(results)
    Path(path).write_bytes(line_chart(series, title=title))
    return len(series)
