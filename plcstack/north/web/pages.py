"""The console's HTML: the frame of every page, the overview ``/``, and the parts both pages use.

Rendered on the server with every PLC name, tag name, description, unit, value and error text
passed through :func:`html.escape` (a name holding ``<script>`` is shown as text, never run) and
every name in a link percent-encoded. The pages work as a snapshot without JavaScript (times in
UTC, the filter a plain form); the one script (``/static/console.js``, no build step, no
third-party code) keeps them live from the server-sent events, shows times in the browser's
time zone with their age, filters and pages the overview, draws the charts and asks before a
write. It writes into the page only through ``textContent`` and a ``<template>`` of each row the
server renders, so the layout of a row exists once. The Content-Security-Policy the server
sends allows no inline script at all.

The overview shows counts of PLCs by state, a filter, and one page of PLC rows (see
:mod:`.overview`): at a thousand PLCs it stays a few tens of kilobytes.
"""

from __future__ import annotations

import datetime
import html
from collections.abc import Iterable, Mapping
from urllib.parse import quote, urlencode

from plcstack.north.web.overview import PAGE_SIZE, SORTS, Selection
from plcstack.north.web.state import ConsoleState, PlcRow

__all__ = [
    "PLC_HEAD",
    "PLC_HEAD_NO_ERROR",
    "document",
    "error_text",
    "esc",
    "format_time",
    "overview_page",
    "plc_rows_html",
    "time_tag",
]

#: the head of a PLC table; the cells of a row have these classes (the script fills them)
PLC_HEAD = (
    "<tr><th>PLC</th><th>state</th><th>since</th><th>tags</th><th>error</th>"
    '<th class="num">requests</th><th class="num">errors</th><th class="num">p99 ms</th></tr>'
)
#: the same without the error (the PLC's page says it once, above)
PLC_HEAD_NO_ERROR = PLC_HEAD.replace("<th>error</th>", "")
_STAT_CELLS = ("requests", "errors", "p99_ms")
#: the first line of an error shown in a cell; the whole text on demand
FIRST_LINE = 160


def esc(text: object) -> str:
    return html.escape(str(text), quote=True)


def format_time(t: float | None) -> str:
    """UTC ISO 8601 with milliseconds, as JavaScript's ``Date.toISOString``."""
    if t is None:
        return ""
    moment = datetime.datetime.fromtimestamp(t, datetime.UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def time_tag(t: float | None) -> str:
    """A time the script shows in the browser's zone, with its age; UTC without the script."""
    if t is None:
        return "<time></time>"
    iso = format_time(t)
    return f'<time datetime="{iso}" data-t="{t:.3f}">{iso.replace("T", " ")}</time>'


def error_text(text: str | None) -> str:
    """An error as one line, the full text on demand (a dead PLC's error is ten lines)."""
    if not text:
        return ""
    first = text.strip().splitlines()[0] if text.strip() else text
    if first == text and len(text) <= FIRST_LINE:
        return f'<span class="err">{esc(text)}</span>'
    if len(first) > FIRST_LINE:
        first = first[: FIRST_LINE - 3] + "..."
    return f'<details class="err"><summary>{esc(first)}</summary><pre>{esc(text)}</pre></details>'


def document(
    title: str,
    body: str,
    *,
    view: str,
    plc: str | None = None,
    trend_seconds: int = 300,
    history: bool = False,
) -> str:
    scope = "" if plc is None else f' data-plc="{esc(plc)}"'
    return (
        "<!doctype html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{esc(title)}</title>"
        '<link rel="stylesheet" href="/static/console.css">'
        '<script src="/static/console.js" defer></script></head>'
        f'<body data-view="{view}"{scope} data-trend-seconds="{trend_seconds}"'
        f' data-history="{1 if history else 0}">'
        '<header><a class="home" href="/">plcstack</a>'
        f"<h1>{esc(title)}</h1>"
        '<span id="live" class="live">not live</span></header>\n'
        f"{body}</body></html>\n"
    )


#: the row the page's template is rendered from (the script fills its cells)
_EMPTY_ROW: PlcRow = {
    "name": "",
    "tags": 0,
    "up": None,
    "state": "unknown",
    "since": None,
    "last_error": None,
    "error_time": None,
    "bad_tags": 0,
}


def plc_rows_html(rows: Iterable[PlcRow], *, link: bool, error: bool = True) -> str:
    """PLC rows: state, since when, tags (and how many are bad), the error while it matters
    (offline, or some tags bad; not with ``error=False``), requests, errors, p99."""
    out = []
    for r in rows:
        name = esc(r["name"])
        label = f'<a href="/plc/{esc(quote(r["name"], safe=""))}">{name}</a>' if link else name
        state = r["state"]
        bad = r["bad_tags"]
        tags = f"{r['tags'] if r['name'] else ''}" + (f" ({bad} bad)" if bad else "")
        last = r["last_error"] if state in ("offline", "errors") else None
        error_cell = f'<td class="last_error">{error_text(last)}</td>' if error else ""
        values: Mapping[str, object] = r
        cells = "".join(
            f'<td class="{c} num">{esc("" if values.get(c) is None else values[c])}</td>'
            for c in _STAT_CELLS
        )
        out.append(
            f'<tr data-plc="{name}"><td class="name">{label}</td>'
            f'<td class="state {state}">{state}</td><td class="since">{time_tag(r["since"])}</td>'
            f'<td class="tags num">{esc(tags)}</td>{error_cell}'
            f"{cells}</tr>"
        )
    return "".join(out)


def _counts(counts: dict[str, int]) -> str:
    words = (
        ("online", "online"),
        ("offline", "offline"),
        ("errors", "with errors"),
        ("unknown", "not polled yet"),
    )
    parts = "".join(
        f'<span class="count {key}"><b id="n-{key}">{counts[key]}</b> {word}</span>'
        for key, word in words
    )
    return f'<p id="counts">{parts}<span class="count total">of {counts["total"]} PLCs</span></p>'


def _link(selection: Selection, page: int) -> str:
    params = {"q": selection.query, "sort": selection.sort, "page": str(page)}
    return "/?" + urlencode({k: v for k, v in params.items() if v and v != "state"})


def pager(selection: Selection) -> str:
    """ "PLCs 51-100 of 200" with the links to the pages before and after."""
    last = selection.first + len(selection.names) - 1
    text = (
        f"PLCs {selection.first}-{last} of {selection.matched}"
        if selection.names
        else "no PLC matches"
    )
    prev = (
        f'<a rel="prev" href="{esc(_link(selection, selection.page - 1))}">previous</a>'
        if selection.page > 1
        else ""
    )
    nxt = (
        f'<a rel="next" href="{esc(_link(selection, selection.page + 1))}">next</a>'
        if selection.page < selection.pages
        else ""
    )
    return (
        f'<p id="pager" data-page="{selection.page}" data-pages="{selection.pages}">'
        f'<span class="shown">{text}</span> {prev} {nxt}</p>'
    )


def overview_page(
    state: ConsoleState,
    selection: Selection,
    rows: list[PlcRow],
    *,
    trend_seconds: int,
    history: bool,
) -> str:
    """``/``: the counts, the filter, one page of PLC rows (see :mod:`.overview`)."""
    options = "".join(
        f'<option value="{key}"{" selected" if key == selection.sort else ""}>{esc(text)}</option>'
        for key, text in SORTS.items()
    )
    template = plc_rows_html([_EMPTY_ROW], link=True)
    body = (
        f"{_counts(state.counts())}"
        '<form id="filter" method="get" action="/" role="search">'
        f'<input name="q" type="search" placeholder="filter: name, address or state"'
        f' aria-label="filter PLCs" value="{esc(selection.query)}" autocomplete="off">'
        f'<select name="sort" aria-label="order">{options}</select>'
        '<button type="submit">filter</button></form>'
        f"{pager(selection)}"
        f'<table id="plcs" data-page-size="{PAGE_SIZE}"><thead>{PLC_HEAD}</thead><tbody>'
        f"{plc_rows_html(rows, link=True)}</tbody></table>"
        f'<template id="plc-row">{template}</template>\n'
    )
    return document(
        "plcstack console", body, view="overview", trend_seconds=trend_seconds, history=history
    )
