// plcstack web console: keeps the server-rendered page live from /events (server-sent events),
// draws the trend charts, sends the write forms. No build step, no libraries. Every name and
// value goes into the page through textContent (shown as text, never parsed as HTML).
"use strict";
(() => {
  const body = document.body;
  const scope = body.dataset.plc; // undefined on the overview
  const windowSeconds = Number(body.dataset.trendSeconds) || 300;
  const SVG = "http://www.w3.org/2000/svg";
  const key = (plc, tag) => plc + "\u0000" + tag;

  const tagRows = new Map();
  for (const tr of document.querySelectorAll("#tags tbody tr")) {
    tagRows.set(key(tr.dataset.plc, tr.dataset.tag), tr);
  }
  const plcRows = new Map();
  for (const tr of document.querySelectorAll("#plcs tbody tr")) plcRows.set(tr.dataset.plc, tr);
  const charts = new Map();
  for (const svg of document.querySelectorAll("svg.trend")) {
    const tr = svg.closest("tr");
    charts.set(key(tr.dataset.plc, tr.dataset.tag), {
      svg, points: JSON.parse(svg.dataset.points || "[]"),
    });
  }

  const formatValue = (v) => {
    if (v === null || v === undefined) return "";
    if (typeof v === "boolean") return v ? "true" : "false";
    if (Array.isArray(v)) return JSON.stringify(v);
    return String(v);
  };
  const formatTime = (t) => (t === null || t === undefined ? "" : new Date(t * 1000).toISOString());
  const setCell = (tr, name, text, extraClass) => {
    const td = tr.querySelector("td." + name);
    if (!td) return;
    if (td.textContent !== text) td.textContent = text;
    if (extraClass !== undefined) td.className = name + " " + extraClass;
  };

  function onTags(rows) {
    const moved = new Set();
    for (const [plc, tag, value, quality, time, error] of rows) {
      const k = key(plc, tag);
      const tr = tagRows.get(k);
      if (!tr) continue;
      setCell(tr, "value", formatValue(value), "num");
      setCell(tr, "quality", quality, quality);
      setCell(tr, "source_time", formatTime(time));
      setCell(tr, "error", error || "");
      const chart = charts.get(k);
      const numeric = typeof value === "number" || typeof value === "boolean";
      if (chart && quality === "good" && numeric) {
        const last = chart.points[chart.points.length - 1];
        if (!last || time > last[0]) chart.points.push([time, Number(value)]);
        moved.add(chart);
      }
    }
    const now = Date.now() / 1000;
    for (const chart of moved) draw(chart, Math.max(now, chart.points[chart.points.length - 1][0]));
  }

  function onPlcs(rows) {
    for (const row of rows) {
      const tr = plcRows.get(row.name);
      if (!tr) continue;
      const state = row.up === null ? "unknown" : row.up ? "online" : "offline";
      setCell(tr, "state", state, state);
      setCell(tr, "last_error", row.last_error || "");
      for (const name of ["requests", "errors", "reconnects", "p50_ms", "p99_ms"]) {
        setCell(tr, name, row[name] === null || row[name] === undefined ? "" : String(row[name]));
      }
    }
  }

  // A step line: a value holds until the next change (the stream carries changes only).
  function draw(chart, now) {
    const W = 300, H = 60, from = now - windowSeconds;
    const points = chart.points;
    let first = 0;
    while (first + 1 < points.length && points[first + 1][0] <= from) first++;
    if (first > 0) points.splice(0, first);
    const svg = chart.svg;
    svg.replaceChildren();
    svg.dataset.count = String(points.length);
    if (!points.length) return;
    let lo = Infinity, hi = -Infinity;
    for (const [, v] of points) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    const flat = hi === lo;
    if (flat) { lo -= 1; hi += 1; }
    const x = (t) => Math.max(0, ((t - from) / windowSeconds) * W).toFixed(1);
    const y = (v) => (H - 4 - ((v - lo) / (hi - lo)) * (H - 8)).toFixed(1);
    const coords = [];
    let previous = null;
    for (const [t, v] of points) {
      const X = x(t), Y = y(v);
      if (previous !== null) coords.push(X + "," + previous);
      coords.push(X + "," + Y);
      previous = Y;
    }
    coords.push(W + "," + previous);
    const line = document.createElementNS(SVG, "polyline");
    line.setAttribute("points", coords.join(" "));
    const title = document.createElementNS(SVG, "title");
    title.textContent = flat ? "constant " + (lo + 1) : "min " + lo + ", max " + hi;
    svg.append(title, line);
  }
  const drawAll = () => {
    const now = Date.now() / 1000;
    for (const chart of charts.values()) {
      const last = chart.points[chart.points.length - 1];
      draw(chart, last ? Math.max(now, last[0]) : now);
    }
  };
  if (charts.size) { drawAll(); setInterval(drawAll, 1000); }

  const live = document.getElementById("live");
  const url = "/events" + (scope === undefined ? "" : "?plc=" + encodeURIComponent(scope));
  const events = new EventSource(url);
  events.addEventListener("open", () => { live.textContent = "live"; live.className = "live on"; });
  events.addEventListener("error", () => {
    live.textContent = "reconnecting"; live.className = "live off";
  });
  events.addEventListener("tags", (e) => { onTags(JSON.parse(e.data)); });
  events.addEventListener("plcs", (e) => { onPlcs(JSON.parse(e.data)); });

  for (const form of document.querySelectorAll("form.write")) {
    form.addEventListener("submit", async (event) => {
      event.preventDefault();
      const tr = form.closest("tr");
      const out = form.querySelector("output");
      const text = form.elements.value.value;
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
    });
  }
})();
