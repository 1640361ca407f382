// plcstack web console: keeps the server-rendered pages live from /events (server-sent events),
// shows times in the browser's time zone with their age, filters and pages the overview, draws
// the charts and asks before a write. No build step, no libraries. Every name and value goes
// into the page through textContent or a clone of a <template> the server rendered (shown as
// text, never parsed as HTML). The server formats every value; this script formats only times
// and the ticks of a chart's axes.
"use strict";
(() => {
  const body = document.body;
  const view = body.dataset.view;
  const scope = body.dataset.plc; // undefined on the overview
  const hasHistory = body.dataset.history === "1";
  const trendSeconds = Number(body.dataset.trendSeconds) || 300;
  const SVG = "http://www.w3.org/2000/svg";
  const key = (plc, tag) => plc + "\u0000" + tag;

  // -- times ------------------------------------------------------------------------------
  const pad = (n) => String(n).padStart(2, "0");
  const sameDay = (a, b) => a.getFullYear() === b.getFullYear() &&
    a.getMonth() === b.getMonth() && a.getDate() === b.getDate();
  function localTime(t, withSeconds = true) {
    const d = new Date(t * 1000);
    const clock = pad(d.getHours()) + ":" + pad(d.getMinutes()) +
      (withSeconds ? ":" + pad(d.getSeconds()) : "");
    if (sameDay(d, new Date())) return clock;
    return d.getFullYear() + "-" + pad(d.getMonth() + 1) + "-" + pad(d.getDate()) + " " + clock;
  }
  function age(seconds) {
    const s = Math.max(0, Math.round(seconds));
    if (s < 60) return s + " s";
    if (s < 3600) return Math.floor(s / 60) + " min";
    if (s < 86400) return Math.floor(s / 3600) + " h " + Math.floor((s % 3600) / 60) + " min";
    return Math.floor(s / 86400) + " d " + Math.floor((s % 86400) / 3600) + " h";
  }
  // a <time data-t="unix">: local time and age, the UTC moment as its tooltip
  function showTime(el, t) {
    if (t === null || t === undefined || t === "") {
      el.removeAttribute("data-t");
      el.removeAttribute("datetime");
      el.textContent = "";
      return;
    }
    const iso = new Date(t * 1000).toISOString();
    el.dataset.t = String(t);
    el.setAttribute("datetime", iso);
    el.title = iso;
    el.textContent = localTime(t) + " (" + age(Date.now() / 1000 - t) + " ago)";
  }
  const tickTimes = () => {
    for (const el of document.querySelectorAll("time[data-t]")) showTime(el, Number(el.dataset.t));
  };

  // -- errors: the first line, the whole text on demand ---------------------------------------
  function errorNode(text) {
    if (!text) return null;
    const first = text.trim().split("\n")[0];
    if (first === text && text.length <= 160) {
      const span = document.createElement("span");
      span.className = "err";
      span.textContent = text;
      return span;
    }
    const details = document.createElement("details");
    details.className = "err";
    const summary = document.createElement("summary");
    summary.textContent = first.length > 160 ? first.slice(0, 157) + "..." : first;
    const pre = document.createElement("pre");
    pre.textContent = text;
    details.append(summary, pre);
    return details;
  }
  function setError(td, text) {
    if (!td) return;
    const shown = td.firstElementChild;
    const full = shown ? (shown.querySelector("pre") || shown).textContent : "";
    if ((text || "") === full) return; // keep an opened <details> open
    td.replaceChildren(...[errorNode(text)].filter(Boolean));
  }

  // -- PLC rows (the overview and the PLC page's statistics) ---------------------------------
  function fillPlcRow(tr, row) {
    tr.dataset.plc = row.name;
    const link = tr.querySelector("td.name a");
    if (link) {
      link.textContent = row.name;
      link.href = "/plc/" + encodeURIComponent(row.name);
    }
    const state = tr.querySelector("td.state");
    state.textContent = row.state;
    state.className = "state " + row.state;
    showTime(tr.querySelector("td.since time"), row.since);
    const tags = tr.querySelector("td.tags");
    tags.textContent = String(row.tags ?? "") + (row.bad_tags ? " (" + row.bad_tags + " bad)" : "");
    const showError = row.state === "offline" || row.state === "errors";
    setError(tr.querySelector("td.last_error"), showError ? row.last_error : null);
    for (const name of ["requests", "errors", "p99_ms"]) {
      const td = tr.querySelector("td." + name);
      if (td) td.textContent = row[name] === null || row[name] === undefined ? "" : String(row[name]);
    }
  }
  const plcRows = new Map();
  for (const tr of document.querySelectorAll("#plcs tbody tr")) plcRows.set(tr.dataset.plc, tr);
  let banner = null; // the PLC page's state line
  function onPlcs(rows) {
    for (const row of rows) {
      const tr = plcRows.get(row.name);
      if (tr) fillPlcRow(tr, row);
      if (banner && row.name === scope) showBanner(row);
    }
  }

  // -- the overview: counts, filter, pages ---------------------------------------------------
  function onCounts(counts) {
    for (const [name, n] of Object.entries(counts)) {
      const el = document.getElementById("n-" + name);
      if (el) el.textContent = String(n);
    }
  }
  function setupOverview() {
    const form = document.getElementById("filter");
    const tbody = document.querySelector("#plcs tbody");
    const template = document.getElementById("plc-row");
    const pager = document.getElementById("pager");
    let asked = 0;
    async function load(params) {
      const mine = ++asked;
      const response = await fetch("/api/overview?" + params.toString());
      if (!response.ok || mine !== asked) return;
      const answer = await response.json();
      if (mine !== asked) return;
      plcRows.clear();
      const fresh = [];
      for (const row of answer.rows) {
        const tr = template.content.firstElementChild.cloneNode(true);
        fillPlcRow(tr, row);
        plcRows.set(row.name, tr);
        fresh.push(tr);
      }
      tbody.replaceChildren(...fresh);
      openStream(); // the rows of these PLCs from now on
      onCounts(answer.counts);
      showPager(answer, params);
      const url = "/?" + params.toString();
      history.replaceState(null, "", params.toString() ? url : "/");
    }
    function showPager(answer, params) {
      const last = answer.first + answer.rows.length - 1;
      const parts = [];
      const shown = document.createElement("span");
      shown.className = "shown";
      shown.textContent = answer.rows.length
        ? "PLCs " + answer.first + "-" + last + " of " + answer.matched : "no PLC matches";
      parts.push(shown);
      for (const [rel, page, text] of [
        ["prev", answer.page - 1, "previous"], ["next", answer.page + 1, "next"],
      ]) {
        if (page < 1 || page > answer.pages) continue;
        const link = document.createElement("a");
        const p = new URLSearchParams(params);
        p.set("page", String(page));
        link.rel = rel;
        link.href = "/?" + p.toString();
        link.textContent = text;
        parts.push(document.createTextNode(" "), link);
      }
      pager.replaceChildren(...parts);
      pager.dataset.page = String(answer.page);
      pager.dataset.pages = String(answer.pages);
    }
    const params = (page) => {
      const p = new URLSearchParams();
      const q = form.elements.q.value.trim();
      if (q) p.set("q", q);
      if (form.elements.sort.value !== "state") p.set("sort", form.elements.sort.value);
      if (page > 1) p.set("page", String(page));
      return p;
    };
    let timer = null;
    form.elements.q.addEventListener("input", () => {
      clearTimeout(timer);
      timer = setTimeout(() => load(params(1)), 200);
    });
    form.elements.sort.addEventListener("change", () => load(params(1)));
    form.addEventListener("submit", (event) => { event.preventDefault(); load(params(1)); });
    pager.addEventListener("click", (event) => {
      const link = event.target.closest("a");
      if (!link) return;
      event.preventDefault();
      load(new URLSearchParams(new URL(link.href).search));
    });
  }

  // -- the PLC page: state line, tag rows ----------------------------------------------------
  function showBanner(row) {
    const offline = row.state === "offline";
    banner.className = offline ? "offline" : "";
    banner.querySelector(".b-state").textContent = offline ? "offline since " : "";
    const since = banner.querySelector(".b-since");
    let time = since.querySelector("time");
    if (!time) { time = document.createElement("time"); since.replaceChildren(time); }
    showTime(time, offline ? row.since : null);
    setError(banner.querySelector(".b-error"), offline ? row.last_error : null);
    if (plcOffline === offline) return;
    plcOffline = offline;
    for (const [k, tr] of tagRows) { // an offline PLC's error is said once, in the state line
      setError(tr.querySelector("td.error"), offline ? null : tagErrors.get(k));
    }
  }
  let plcOffline = false;
  const tagRows = new Map();
  const tagErrors = new Map(); // each tag's latest error (shown unless it is the PLC's)
  for (const tr of document.querySelectorAll("#tags tbody tr")) {
    tagRows.set(key(tr.dataset.plc, tr.dataset.tag), tr);
  }
  function onTags(rows) {
    const moved = new Set();
    for (const [plc, tag, value, quality, time, error, text, goodTime, staleSince] of rows) {
      const k = key(plc, tag);
      const tr = tagRows.get(k);
      if (tr) {
        tr.className = quality;
        const cell = tr.querySelector("td.value");
        cell.querySelector(".text").textContent = text;
        const stale = staleSince !== null && staleSince !== undefined && text !== "";
        cell.classList.toggle("stale", stale);
        const note = cell.querySelector(".stale-note");
        if (stale) {
          let t = note.querySelector("time");
          if (!t) {
            t = document.createElement("time");
            note.replaceChildren(document.createTextNode("stale since "), t);
          }
          showTime(t, staleSince);
        } else {
          note.replaceChildren();
        }
        let t = tr.querySelector("td.time time");
        if (!t) { t = document.createElement("time"); tr.querySelector("td.time").append(t); }
        showTime(t, goodTime);
        tagErrors.set(k, error);
        setError(tr.querySelector("td.error"), plcOffline ? null : error);
      }
      for (const chart of chartsOf.get(k) || []) {
        chart.add(tag, time, quality === "good" ? value : null);
        moved.add(chart);
      }
    }
    for (const chart of moved) chart.draw();
  }

  // -- charts ---------------------------------------------------------------------------------
  const COLOURS = 6;
  const TIME_STEPS = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800,
    21600, 43200, 86400];
  const number = (v) => {
    if (typeof v === "boolean") return v ? 1 : 0;
    if (typeof v === "number") return v;
    return null; // "NaN", "Infinity", text: a gap
  };
  function niceStep(span, count) {
    const raw = span / count;
    const magnitude = Math.pow(10, Math.floor(Math.log10(raw)));
    for (const m of [1, 2, 2.5, 5, 10]) if (m * magnitude >= raw) return m * magnitude;
    return 10 * magnitude;
  }
  const svgEl = (name, attrs, text) => {
    const el = document.createElementNS(SVG, name);
    for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, String(v));
    if (text !== undefined) el.textContent = text;
    return el;
  };
  class Chart {
    constructor(figure) {
      this.figure = figure;
      this.svg = figure.querySelector("svg");
      this.tags = JSON.parse(figure.dataset.tags);
      this.unit = figure.dataset.unit;
      this.steps = figure.dataset.steps === "1";
      this.labels = JSON.parse(figure.dataset.labels || "{}");
      const points = JSON.parse(figure.dataset.points || "{}");
      this.series = new Map(this.tags.map((t) => [t, (points[t] || []).map(([x, v]) => [x, number(v)])]));
      this.range = trendSeconds;
    }
    add(tag, t, value) {
      const points = this.series.get(tag);
      if (!points) return;
      const last = points[points.length - 1];
      const v = value === null ? null : number(value);
      if (last && t <= last[0]) return;
      if (last && last[1] === v) return; // a step line needs only the changes
      points.push([t, v]);
    }
    async load(range) {
      this.range = range;
      const to = Date.now() / 1000;
      const width = Math.max(200, this.svg.clientWidth || 600);
      const answers = await Promise.all(this.tags.map(async (tag) => {
        const url = "/api/history?plc=" + encodeURIComponent(scope) + "&tag=" +
          encodeURIComponent(tag) + "&from=" + (to - range) + "&to=" + to + "&points=" +
          Math.round(width);
        const response = await fetch(url);
        if (!response.ok) return [tag, null];
        return [tag, (await response.json()).points];
      }));
      for (const [tag, points] of answers) {
        if (points === null) continue;
        const live = this.series.get(tag).filter(([t]) => t > to);
        this.series.set(tag, points.map(([t, v]) => [t, number(v)]).concat(live));
      }
      this.figure.dataset.loaded = String(range);
      this.draw();
    }
    draw() {
      const svg = this.svg;
      const W = Math.max(200, svg.clientWidth || 600), H = this.steps ? 96 : 220;
      svg.setAttribute("viewBox", "0 0 " + W + " " + H);
      svg.setAttribute("height", String(H));
      const L = 64, R = 12, T = 16, B = 22;
      const to = Date.now() / 1000, from = to - this.range;
      let lo = Infinity, hi = -Infinity, count = 0;
      for (const points of this.series.values()) {
        let first = 0;
        while (first + 1 < points.length && points[first + 1][0] <= from) first++;
        if (first > 0) points.splice(0, first); // keeps the point that held at `from`
        for (const [, v] of points) {
          if (v === null || !Number.isFinite(v)) continue;
          lo = Math.min(lo, v); hi = Math.max(hi, v); count++;
        }
      }
      const labelKeys = Object.keys(this.labels).map(Number);
      if (this.steps && labelKeys.length) {
        lo = Math.min(lo, ...labelKeys); hi = Math.max(hi, ...labelKeys);
      }
      if (!count && !labelKeys.length) { lo = 0; hi = 1; }
      if (hi === lo) { lo -= 1; hi += 1; }
      if (this.steps) { const m = (hi - lo) * 0.15; lo -= m; hi += m; }
      const x = (t) => L + ((Math.max(t, from) - from) / (to - from)) * (W - L - R);
      const y = (v) => T + (1 - (v - lo) / (hi - lo)) * (H - T - B);
      const out = [];
      // value axis: the states' names, or nice numbers; the unit above it
      const ticks = [];
      if (this.steps && labelKeys.length) {
        for (const k of labelKeys) ticks.push([k, this.labels[String(k)]]);
      } else {
        const step = niceStep(hi - lo, 4);
        for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) {
          ticks.push([v, String(Number(v.toPrecision(12)))]);
        }
      }
      const axis = svgEl("g", { class: "axis y" });
      for (const [v, text] of ticks) {
        axis.append(svgEl("line", { x1: L, x2: W - R, y1: y(v), y2: y(v), class: "grid" }));
        axis.append(svgEl("text", { x: L - 6, y: y(v) + 4, "text-anchor": "end" }, text));
      }
      if (this.unit) axis.append(svgEl("text", { x: 4, y: 11, class: "unit" }, this.unit));
      out.push(axis);
      // time axis: local times at a round step
      const span = to - from;
      const step = TIME_STEPS.find((s) => span / s <= 7) || 86400;
      const offset = new Date().getTimezoneOffset() * 60;
      const timeAxis = svgEl("g", { class: "axis x" });
      timeAxis.append(svgEl("line", { x1: L, x2: W - R, y1: H - B, y2: H - B }));
      for (let t = Math.ceil((from - offset) / step) * step + offset; t <= to; t += step) {
        const X = x(t);
        timeAxis.append(svgEl("line", { x1: X, x2: X, y1: T, y2: H - B, class: "grid" }));
        timeAxis.append(svgEl("text", { x: X, y: H - 6, "text-anchor": "middle" },
          localTime(t, step < 60)));
      }
      out.push(timeAxis);
      // each series: a step line (a value holds until the next point), broken where bad
      let index = 0;
      for (const points of this.series.values()) {
        let d = "", open = false, lastY = null;
        for (const [t, v] of points) {
          const X = x(t).toFixed(1);
          if (v === null || !Number.isFinite(v)) {
            if (open) d += "H" + X;
            open = false;
            continue;
          }
          const Y = y(v).toFixed(1);
          if (!open) { d += "M" + X + " " + Y; open = true; } else { d += "H" + X + "V" + Y; }
          lastY = Y;
        }
        if (open && lastY !== null) d += "H" + (W - R);
        const path = svgEl("path", { d: d || "M0 0", class: "line s" + (index % COLOURS) });
        out.push(path);
        index++;
      }
      svg.replaceChildren(...out);
      this.figure.dataset.count = String(count);
    }
  }
  const charts = [...document.querySelectorAll("figure.chart")].map((f) => new Chart(f));
  const chartsOf = new Map();
  for (const chart of charts) {
    for (const tag of chart.tags) {
      const k = key(scope, tag);
      if (!chartsOf.has(k)) chartsOf.set(k, []);
      chartsOf.get(k).push(chart);
    }
  }
  function setupRanges() {
    const group = document.querySelector("#trends .ranges[role=group]");
    if (!group || !hasHistory) { for (const c of charts) c.draw(); return; }
    const choose = (button) => {
      for (const b of group.querySelectorAll("button")) {
        b.setAttribute("aria-pressed", b === button ? "true" : "false");
      }
      const range = Number(button.dataset.range);
      for (const c of charts) c.load(range);
    };
    group.addEventListener("click", (event) => {
      const button = event.target.closest("button[data-range]");
      if (button) choose(button);
    });
    choose(group.querySelector("button[aria-pressed=true]") || group.querySelector("button"));
  }

  // -- writes: confirmed first, then sent ------------------------------------------------------
  function setupWrites() {
    const dialog = document.getElementById("confirm");
    for (const form of document.querySelectorAll("form.write")) {
      form.addEventListener("submit", (event) => {
        event.preventDefault();
        const tr = form.closest("tr");
        const text = form.elements.value.value;
        dialog.querySelector(".c-tag").textContent = tr.dataset.tag;
        dialog.querySelector(".c-plc").textContent = tr.dataset.plc;
        dialog.querySelector(".c-old").textContent =
          tr.querySelector("td.value .text").textContent || "(no value yet)";
        const unit = tr.dataset.unit;
        const number = text.trim() !== "" && Number.isFinite(Number(text));
        dialog.querySelector(".c-new").textContent = number && unit ? text.trim() + " " + unit : text;
        dialog.returnValue = "";
        dialog.onclose = () => {
          const out = form.querySelector("output");
          if (dialog.returnValue === "write") send(form, tr, text);
          else { out.textContent = "not written"; out.className = ""; }
        };
        dialog.showModal();
        dialog.querySelector(".c-cancel").focus();
      });
    }
  }
  async function send(form, tr, text) {
    const out = form.querySelector("output");
    let value;
    try { value = JSON.parse(text); } catch { value = text; }
    const token = (document.getElementById("token") || {}).value || "";
    const headers = { "Content-Type": "application/json" };
    if (token) headers.Authorization = "Bearer " + token;
    out.textContent = "writing";
    out.className = "";
    const path = "/api/plcs/" + encodeURIComponent(tr.dataset.plc) +
      "/tags/" + encodeURIComponent(tr.dataset.tag);
    try {
      const response = await fetch(path, {
        method: "POST", headers, body: JSON.stringify({ value }),
      });
      const answer = await response.json();
      if (answer.ok) {
        out.textContent = "written";
        out.className = "ok";
      } else {
        out.textContent = answer.error + ": " + answer.message +
          (answer.may_have_executed ? " (it may have been executed)" : "");
        out.className = "refused";
      }
    } catch (error) {
      out.textContent = "no answer: " + error;
      out.className = "refused";
    }
  }

  // -- the stream: an overview asks for the rows it shows, a PLC's page for that PLC ------------
  let events = null;
  function openStream() {
    if (events) events.close();
    const live = document.getElementById("live");
    let url = "/events?plc=" + encodeURIComponent(scope);
    if (view === "overview") {
      const names = [...plcRows.keys()]; // none shown: "&show=" alone, no rows
      url = "/events?view=overview" + (names.length
        ? names.map((n) => "&show=" + encodeURIComponent(n)).join("") : "&show=");
    }
    events = new EventSource(url);
    events.addEventListener("open", () => { live.textContent = "live"; live.className = "live on"; });
    events.addEventListener("error", () => {
      live.textContent = "reconnecting"; live.className = "live off";
    });
    events.addEventListener("tags", (e) => { onTags(JSON.parse(e.data)); });
    events.addEventListener("plcs", (e) => { onPlcs(JSON.parse(e.data)); });
    events.addEventListener("counts", (e) => { onCounts(JSON.parse(e.data)); });
  }

  // -- start ------------------------------------------------------------------------------------
  tickTimes();
  setInterval(() => { tickTimes(); for (const c of charts) c.draw(); }, 1000);
  if (view === "overview") setupOverview();
  if (view === "plc") {
    banner = document.getElementById("banner");
    plcOffline = banner.classList.contains("offline");
    setupRanges();
    setupWrites();
  }
  openStream();
})();
