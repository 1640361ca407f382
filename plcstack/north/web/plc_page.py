"""``/plc/NAME``: one PLC as an operator works with it.

* One line of state: online or offline since when, and while offline the error once (its
  first line; the whole text on demand), not repeated in every tag row.
* Charts with a time axis and a value axis with the unit: the numeric tags of one unit share
  a chart (up to :data:`PER_CHART`), a ``bool`` or a tag with ``labels`` gets a step chart of
  its own; ranges from minutes to a day when the gateway keeps a history (``[history]``),
  else the last ``trend_seconds`` the console holds in memory.
* The tags: the value in its display form with its unit, kept and marked stale (since when)
  while the tag is bad, the time of the value with its age, and a write form for each tag with
  ``writable = true``, which asks for confirmation showing the tag, its value now and the
  new one before anything is sent.
"""

from __future__ import annotations

import json
from urllib.parse import quote

from plcstack.north.web.pages import (
    PLC_HEAD_NO_ERROR,
    document,
    error_text,
    esc,
    plc_rows_html,
    time_tag,
)
from plcstack.north.web.state import ConsoleState, PlcRow
from plcstack.poll.config import TagConfig

__all__ = ["PER_CHART", "RANGES", "plc_page"]

#: tags of one unit drawn on one chart at most (more get another chart)
PER_CHART = 6
#: the ranges a chart offers with a history, seconds: label
RANGES = {300: "5 min", 900: "15 min", 3600: "1 h", 8 * 3600: "8 h", 86400: "24 h"}
#: the range shown first with a history
DEFAULT_RANGE = 900
_NUMERIC = ("int", "float", "raw", "bool")
_PATTERNS = ("kh", "km")


def _charted(tag: TagConfig) -> bool:
    """A number that moves: not an array, not a bit pattern (``kh``, ``km``)."""
    return tag.count == 1 and tag.type.kind in _NUMERIC and tag.type.name not in _PATTERNS


def chart_groups(state: ConsoleState, plc: str) -> list[list[TagConfig]]:
    """The charts of a PLC's page: the numeric tags of one unit together (in the order of the
    configuration, at most :data:`PER_CHART` a chart), each step tag alone."""
    groups: list[list[TagConfig]] = []
    by_unit: dict[str, list[TagConfig]] = {}
    for tag in state.plcs[plc].tags:
        if not _charted(tag):
            continue
        if state.displays[(plc, tag.name)].steps:
            groups.append([tag])
            continue
        group = by_unit.get(tag.unit or "")
        if group is None or len(group) >= PER_CHART:
            group = by_unit[tag.unit or ""] = []
            groups.append(group)
        group.append(tag)
    return groups


def _chart(state: ConsoleState, plc: str, tags: list[TagConfig]) -> str:
    display = state.displays[(plc, tags[0].name)].chart()
    points = {t.name: [[round(x, 3), v] for x, v in state.trend(plc, t.name)] for t in tags}
    legend = "".join(
        f'<span class="key s{i}"><i></i>{esc(t.name)}</span>' for i, t in enumerate(tags)
    )
    unit = display["unit"]
    title = ", ".join(t.name for t in tags) + (f" ({unit})" if unit else "")
    return (
        f'<figure class="chart{" steps" if display["steps"] else ""}"'
        f' data-tags="{esc(json.dumps([t.name for t in tags]))}"'
        f' data-unit="{esc(unit)}" data-steps="{1 if display["steps"] else 0}"'
        f' data-labels="{esc(json.dumps(display.get("labels", {})))}"'
        f' data-points="{esc(json.dumps(points))}">'
        f"<figcaption>{legend}</figcaption>"
        f'<svg role="img" aria-label="chart of {esc(title)}"></svg></figure>'
    )


def _ranges(history: bool, trend_seconds: int) -> str:
    if not history:
        return (
            f'<p class="ranges">the last {trend_seconds} s (keep more with a [history] table)</p>'
        )
    pressed = ' aria-pressed="true"'
    buttons = "".join(
        f'<button type="button" data-range="{seconds}"'
        f"{pressed if seconds == DEFAULT_RANGE else ''}>{label}</button>"
        for seconds, label in RANGES.items()
    )
    return f'<p class="ranges" role="group" aria-label="range">{buttons}</p>'


def _tag_row(state: ConsoleState, plc: str, tag: TagConfig, plc_error: str | None) -> str:
    key = (plc, tag.name)
    sample = state.latest.get(key)
    text, good_time, stale = state.text(sample) if sample is not None else ("", None, None)
    stale_note = (
        f'<span class="stale-note">stale since {time_tag(stale)}</span>'
        if stale is not None and text
        else '<span class="stale-note"></span>'
    )
    # an offline PLC's error is said once, in the state line, not in every tag's row
    error = sample.error if sample is not None and plc_error is None else None
    quality = "" if sample is None else sample.quality.value
    form = ""
    if tag.writable:
        form = (
            '<form class="write" method="post" autocomplete="off">'
            f'<input name="value" aria-label="new value of {esc(tag.name)}" required>'
            '<button type="submit">write...</button><output></output></form>'
        )
    description = (
        f'<small class="description">{esc(tag.description)}</small>' if tag.description else ""
    )
    return (
        f'<tr data-plc="{esc(plc)}" data-tag="{esc(tag.name)}" data-unit="{esc(tag.unit or "")}"'
        f' class="{quality}">'
        f'<td class="tag">{esc(tag.name)}{description}</td>'
        f'<td class="value{" stale" if stale is not None and text else ""}">'
        f'<span class="text">{esc(text)}</span>{stale_note}</td>'
        f'<td class="time">{time_tag(good_time)}</td>'
        f'<td class="address">{esc(tag.address)}</td>'
        f'<td class="error">{error_text(error)}</td><td>{form}</td></tr>'
    )


_CONFIRM = (
    '<dialog id="confirm" aria-labelledby="confirm-title"><form method="dialog">'
    '<p id="confirm-title">Write to <b class="c-tag"></b> of <b class="c-plc"></b>?</p>'
    '<table><tr><th>value now</th><td class="c-old"></td></tr>'
    '<tr><th>new value</th><td class="c-new"></td></tr></table>'
    '<p class="c-note">The PLC executes it at once.</p>'
    '<button value="cancel" class="c-cancel">cancel</button> '
    '<button value="write" class="c-write">write</button></form></dialog>'
)


def plc_page(
    state: ConsoleState,
    plc: str,
    plc_rows: list[PlcRow],
    *,
    trend_seconds: int,
    writes_enabled: bool,
    history: bool,
    capture: bool = False,
) -> str:
    """``/plc/NAME`` (see the module's docstring)."""
    config = state.plcs[plc]
    health = state.health[plc]
    plc_error = health.last_error if health.up is False else None
    rows = [_tag_row(state, plc, tag, plc_error) for tag in config.tags]
    charts = "".join(_chart(state, plc, group) for group in chart_groups(state, plc))
    token = ""
    if any(tag.writable for tag in config.tags):
        token = (
            '<p class="token"><label>write token <input id="token" type="password"'
            ' autocomplete="off"></label> '
            + (
                "writes go to the PLC through the poller's connection, after you confirm"
                if writes_enabled
                else "writes are off: the console was started without a write token"
            )
            + "</p>"
        )
    banner = (
        f'<div id="banner" class="{"offline" if plc_error else ""}">'
        f'<span class="b-state">{"offline since " if plc_error else ""}</span>'
        f'<span class="b-since">{time_tag(health.since) if plc_error else ""}</span> '
        f'<div class="b-error">{error_text(plc_error)}</div></div>'
    )
    body = (
        f"{banner}"
        f'<table id="plcs"><thead>{PLC_HEAD_NO_ERROR}</thead><tbody>'
        f"{plc_rows_html(plc_rows, link=False, error=False)}</tbody></table>\n"
        f'<p class="url">{esc(config.url)}</p>'
        + (
            f'<p class="capture"><a href="/api/plcs/{esc(quote(plc, safe=""))}/capture.pcapng"'
            " download>the last frames of its connection (pcapng, for Wireshark)</a></p>"
            if capture
            else ""
        )
        + f'<section id="trends">{_ranges(history, trend_seconds)}{charts}</section>\n'
        f"{token}"
        '<table id="tags"><thead><tr><th>tag</th><th>value</th><th>changed</th>'
        "<th>address</th><th>error</th><th>write</th></tr></thead><tbody>"
        + "".join(rows)
        + f"</tbody></table>\n{_CONFIRM}\n"
    )
    return document(plc, body, view="plc", plc=plc, trend_seconds=trend_seconds, history=history)
