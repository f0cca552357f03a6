(function () {
  "use strict";
  const D = JSON.parse(document.getElementById("report-data").textContent);
  const byId = {};
  D.missions.forEach((m) => { byId[m.id] = m; });
  const el = (tag, text, cls) => {
    const e = document.createElement(tag);
    if (text !== undefined && text !== null) e.textContent = text;
    if (cls) e.className = cls;
    return e;
  };
  // a legend entry: a coloured mark (class "swatch": a bar; "sym": a dot) and its text
  const entry = (tag, colour, text, mark) => {
    const box = el(tag);
    const sw = el("span", undefined, mark || "swatch");
    sw.style.background = colour;
    box.appendChild(sw);
    box.appendChild(document.createTextNode(text));
    return box;
  };
  const fmt = (v, digits) => (v === null || v === undefined ? "" : Number(v).toFixed(digits));
  const km = (v) => (v === null || v === undefined ? "" : (v / 1000).toFixed(2));
  const pct = (v) => (v === null || v === undefined ? "" : (100 * v).toFixed(0));
  const hours = (v) => (v === null || v === undefined ? "" : (v / 3600).toFixed(1));

  // ---------------------------------------------------------------- header
  document.getElementById("title").textContent = D.title;
  const count = (s) => D.missions.filter((m) => m.status === s).length;
  document.getElementById("summary").textContent =
    D.missions.length + " missions: " + count("ok") + " ok (certified), " +
    count("uncertified") + " uncertified, " + count("failed") + " failed. " +
    "Coordinates are the maps' own, in kilometres.";
  const foot = document.getElementById("footer");
  foot.textContent = "Written " + D.written + " by the AUV planning pipeline; no network needed. " +
    "Map: Leaflet 1.9.4 (BSD 2-Clause). ";
  if (D.performance_report) {
    const a = el("a", "dask performance report");
    a.href = "performance-report.html";
    foot.appendChild(a);
    foot.appendChild(document.createTextNode(" (dask's: the run's tasks, workers and timings)."));
  }

  // ---------------------------------------------------------------- map
  const ll = (p) => [p[1] / 1000, p[0] / 1000];  // map metres -> [y km, x km]
  const map = L.map("map", { crs: L.CRS.Simple, minZoom: -10, maxZoom: 8, zoomSnap: 0.25,
                             attributionControl: false });
  let bounds = null;
  const grow = (b) => { bounds = bounds ? bounds.extend(b) : L.latLngBounds(b.getSouthWest(), b.getNorthEast()); };
  const H = D.hillshade;
  if (H) {
    const b = L.latLngBounds(ll([H.extent[0], H.extent[1]]), ll([H.extent[2], H.extent[3]]));
    L.imageOverlay(H.href, b, { alt: "hillshade of the DEM" }).addTo(map);
    grow(b);
  }
  const lines = {};
  let zoned = false;
  D.missions.forEach((m) => {
    (m.zones || []).forEach((z) => {
      zoned = true;
      L.polygon(z.ring.map(ll), { color: "#7b3294", weight: 1, fillOpacity: 0.2,
                                  className: "zone" }).bindTooltip(el("span", "keep-out zone: " + z.name)).addTo(map);
    });
  });
  D.missions.forEach((m) => {
    if (!m.track || m.track.length < 2) return;
    // a white casing under each track keeps it visible over any colour of the hillshade
    L.polyline(m.track.map(ll), { color: "#fff", weight: 6, opacity: 0.8, interactive: false,
                                  className: "casing" }).addTo(map);
    const line = L.polyline(m.track.map(ll), { color: m.colour, weight: 3, opacity: 1,
                                                className: "track track-" + m.id });
    line.bindPopup(() => popup(m));
    line.on("click", () => select(m.id, false));
    line.addTo(map);
    lines[m.id] = line;
    m.waypoint_xy.forEach((w) => L.circleMarker(ll(w), { radius: 2, color: "#222", weight: 0.6,
      fillColor: "#fff", fillOpacity: 1, className: "waypoint" }).addTo(map));
    (m.via_xy || []).forEach((v, k) => L.circleMarker(ll(v), { radius: 5, color: "#000", weight: 1,
      fillColor: "#00bcd4", fillOpacity: 1, className: "via" }).bindTooltip(el("span", m.name + ": via " + (k + 1))).addTo(map));
    L.circleMarker(ll(m.track[0]), { radius: 6, color: "#000", weight: 1, fillColor: "#3c3",
      fillOpacity: 1, className: "start" }).bindTooltip(el("span", m.name + ": start")).addTo(map);
    L.circleMarker(ll(m.track[m.track.length - 1]), { radius: 6, color: "#000", weight: 1,
      fillColor: "#fc0", fillOpacity: 1, className: "goal" }).bindTooltip(el("span", m.name + ": goal")).addTo(map);
    grow(line.getBounds());
  });
  if (bounds) map.fitBounds(bounds, { padding: [10, 10] }); else map.setView([0, 0], 0);
  map.on("mousemove", (e) => {
    document.getElementById("readout").textContent =
      "x " + e.latlng.lng.toFixed(2) + " km, y " + e.latlng.lat.toFixed(2) + " km";
  });

  const legend = L.control({ position: "bottomleft" });
  legend.onAdd = () => {
    const box = el("div", undefined, "legend");
    D.missions.forEach((m) => {
      if (lines[m.id]) box.appendChild(entry("div", m.colour, m.name));
    });
    [["#3c3", "start"], ["#fc0", "goal"], ["#fff", "waypoint"]].forEach(([c, t]) => {
      box.appendChild(entry("div", c, t, "sym"));
    });
    if (zoned) box.appendChild(entry("div", "#7b3294", "keep-out zone", "sym"));
    if (D.missions.some((m) => (m.via_xy || []).length)) box.appendChild(entry("div", "#00bcd4", "via point", "sym"));
    if (H) {
      box.appendChild(el("div", "seabed elevation (m)"));
      const bar = el("div", undefined, "bar");
      bar.style.background = "linear-gradient(to right, " + H.stops.join(", ") + ")";
      box.appendChild(bar);
      const ends = el("div", undefined, "ends");
      ends.appendChild(el("span", H.vmin.toFixed(0)));
      ends.appendChild(el("span", H.vmax.toFixed(0)));
      box.appendChild(ends);
    }
    return box;
  };
  legend.addTo(map);

  // ---------------------------------------------------------------- properties
  function props(m) {
    const rows = [
      ["status", m.status + (m.message ? ": " + m.message : "")],
      ["planner, omega", m.planner + ", " + fmt(m.omega, 2)],
      ["grid path length", km(m.length_m) + " km"],
      ["flown length", m.flown_length_m === null ? "" : km(m.flown_length_m) + " km"],
      ["proven lower bound", m.lower_bound_m === null ? "" : km(m.lower_bound_m) + " km"],
      ["certified ratio", fmt(m.certified_ratio, 4) + " (length / proven lower bound)"],
      ["ridge share", pct(m.ridge_ratio) + " % of the grid path" +
        (m.flown_ridge_ratio === null ? "" : ", " + pct(m.flown_ridge_ratio) + " % flown")],
      ["duration", m.duration_s === null ? "" : hours(m.duration_s) + " h"],
      ["waypoints", m.waypoints === null ? "" : String(m.waypoints)],
      ["min clearance", m.min_clearance_m === null ? "" : fmt(m.min_clearance_m, 1) + " m"],
      ["altitude", m.altitude_median_m == null ? "" :
        fmt(m.altitude_median_m, 0) + " m median, " + fmt(m.altitude_p90_m, 0) + " m 90th percentile"],
      ["vertical reversals", m.vertical_reversals_per_km == null ? "" : fmt(m.vertical_reversals_per_km, 2) + " per km"],
      ["max pitch", m.max_pitch_deg === null ? "" : fmt(m.max_pitch_deg, 1) + " deg"],
      ["energy", m.energy_wh === null ? "" : fmt(m.energy_wh, 0) + " Wh"],
      ["planning time", m.runtime_s === null ? "" : fmt(m.runtime_s, 2) + " s"],
    ];
    return rows.filter((r) => r[1] !== "" && r[1] !== " km");
  }
  function fillProps(t, m) {  // the properties table, in the popup and in the side panel
    t.textContent = "";
    props(m).forEach(([k, v]) => {
      const tr = el("tr");
      tr.appendChild(el("td", k));
      tr.appendChild(el("td", v, k === "status" ? "status-" + m.status : undefined));
      t.appendChild(tr);
    });
    return t;
  }
  function popup(m) {
    const box = el("div");
    box.appendChild(el("strong", m.name));
    box.appendChild(fillProps(el("table", undefined, "props"), m));
    return box;
  }

  // ---------------------------------------------------------------- profile (SVG)
  const NS = "http://www.w3.org/2000/svg";
  const svgEl = (tag, attrs, text) => {
    const e = document.createElementNS(NS, tag);
    Object.entries(attrs).forEach(([k, v]) => e.setAttribute(k, v));
    if (text !== undefined) e.textContent = text;
    return e;
  };
  function nice(lo, hi, n) {
    const raw = (hi - lo) / n, p = Math.pow(10, Math.floor(Math.log10(raw)));
    const step = [1, 2, 5, 10].map((f) => f * p).find((s) => s >= raw) || raw;
    const out = [];
    for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(v);
    return out;
  }
  function profile(p) {
    const W = 1200, Hh = 300, L0 = 64, R0 = 12, T0 = 12, B0 = 46;
    const s = p.s_km;
    const series = [
      ["seabed", "seabed under the track", "#8c6d46"],
      ["required", p.seabed ? "lowest safe height (clearance)" : "safety surface along the grid path", "#1f77b4"],
      ["flown", "flown height", "#d62728"],
    ].filter(([k]) => p[k]);
    const vals = series.flatMap(([k]) => p[k]).filter((v) => v !== null);
    let lo = Math.min(...vals), hi = Math.max(...vals);
    const pad = Math.max(20, 0.06 * (hi - lo));
    lo -= pad; hi += pad;
    const x = (v) => L0 + (W - L0 - R0) * (v - s[0]) / Math.max(s[s.length - 1] - s[0], 1e-9);
    const y = (v) => T0 + (Hh - T0 - B0) * (hi - v) / (hi - lo);
    const svg = svgEl("svg", { viewBox: "0 0 " + W + " " + Hh, role: "img",
                               "aria-label": "depth profile along the track" });
    nice(lo, hi, 6).forEach((v) => {
      svg.appendChild(svgEl("line", { x1: L0, x2: W - R0, y1: y(v), y2: y(v), stroke: "#e5e5e5" }));
      svg.appendChild(svgEl("text", { x: L0 - 6, y: y(v) + 4, "text-anchor": "end", "font-size": 11 }, v.toFixed(0)));
    });
    nice(s[0], s[s.length - 1], 12).forEach((v) => {
      svg.appendChild(svgEl("line", { x1: x(v), x2: x(v), y1: T0, y2: Hh - B0, stroke: "#eee" }));
      svg.appendChild(svgEl("text", { x: x(v), y: Hh - B0 + 16, "text-anchor": "middle", "font-size": 11 }, String(+v.toFixed(3))));
    });
    const path = (arr) => arr.map((v, i) => (v === null ? null : x(s[i]).toFixed(1) + "," + y(v).toFixed(1)))
      .filter((q) => q !== null).join(" ");
    series.forEach(([k, , c]) => {
      if (k === "seabed") {
        const pts = path(p[k]) + " " + x(s[s.length - 1]).toFixed(1) + "," + (Hh - B0) + " " + x(s[0]).toFixed(1) + "," + (Hh - B0);
        svg.appendChild(svgEl("polygon", { points: pts, fill: c, "fill-opacity": 0.75, class: "series-" + k }));
      } else {
        svg.appendChild(svgEl("polyline", { points: path(p[k]), fill: "none", stroke: c,
          "stroke-width": k === "flown" ? 1.8 : 1.2, "stroke-dasharray": k === "flown" ? "" : "5 3",
          class: "series-" + k }));
      }
    });
    svg.appendChild(svgEl("rect", { x: L0, y: T0, width: W - L0 - R0, height: Hh - T0 - B0, fill: "none", stroke: "#444" }));
    svg.appendChild(svgEl("text", { x: (L0 + W - R0) / 2, y: Hh - 8, "text-anchor": "middle", "font-size": 12 }, "distance along the track (km)"));
    svg.appendChild(svgEl("text", { x: 14, y: (T0 + Hh - B0) / 2, "text-anchor": "middle", "font-size": 12,
      transform: "rotate(-90 14 " + (T0 + Hh - B0) / 2 + ")" }, "height (m)"));
    const legendBox = document.getElementById("profile-legend");
    legendBox.textContent = "";
    series.forEach(([, label, c]) => legendBox.appendChild(entry("span", c, label)));
    return svg;
  }

  // ---------------------------------------------------------------- selection
  function select(id, zoom) {
    const m = byId[id];
    document.querySelectorAll("#missions tbody tr").forEach((tr) => tr.classList.toggle("selected", tr.dataset.id === id));
    document.getElementById("details-title").textContent = m.name;
    document.getElementById("details-hint").hidden = true;
    fillProps(document.getElementById("details-props"), m);
    document.getElementById("profile-title").textContent = "Depth profile: " + m.name;
    const fig = document.getElementById("profile-figure");
    const box = document.getElementById("profile");
    box.textContent = "";
    if (m.profile) { box.appendChild(profile(m.profile)); fig.hidden = false; } else { fig.hidden = true; }
    const files = document.getElementById("files");
    files.textContent = "";
    m.files.forEach((f) => {
      const li = el("li");
      const a = el("a", f.title);
      a.href = f.href;
      li.appendChild(a);
      li.appendChild(document.createTextNode(" (" + f.href.split("/").pop() + ")"));
      files.appendChild(li);
    });
    document.getElementById("files-title").hidden = m.files.length === 0;
    Object.entries(lines).forEach(([k, line]) => line.setStyle({ weight: k === id ? 5 : 3 }));
    if (lines[id]) lines[id].bringToFront();
    if (zoom && lines[id]) map.fitBounds(lines[id].getBounds(), { padding: [30, 30] });
  }

  // ---------------------------------------------------------------- table
  const COLS = [
    ["mission", (m) => m.name, false],
    ["status", (m) => m.status, false],
    ["planner", (m) => m.planner, false],
    ["omega", (m) => m.omega, true, 2],
    ["length km", (m) => (m.length_m === null ? null : m.length_m / 1000), true, 2],
    ["flown km", (m) => (m.flown_length_m === null ? null : m.flown_length_m / 1000), true, 2],
    ["certified ratio", (m) => m.certified_ratio, true, 4],
    ["ridge %", (m) => (m.ridge_ratio === null ? null : 100 * m.ridge_ratio), true, 0],
    ["duration h", (m) => (m.duration_s === null ? null : m.duration_s / 3600), true, 1],
    ["waypoints", (m) => m.waypoints, true, 0],
    ["reason / message", (m) => m.message, false],
  ];
  const table = document.getElementById("missions");
  const head = el("tr");
  COLS.forEach(([name], j) => {
    const th = el("th", name);
    th.setAttribute("aria-sort", "none");
    th.addEventListener("click", () => sortBy(j, th));
    head.appendChild(th);
  });
  table.tHead.appendChild(head);
  D.missions.forEach((m) => {
    const tr = el("tr");
    tr.dataset.id = m.id;
    if (m.status === "failed") tr.classList.add("failed");
    COLS.forEach(([name, get, num, digits], j) => {
      const v = get(m);
      const td = el("td", v === null || v === undefined ? "" : num ? Number(v).toFixed(digits) : String(v), num ? "num" : "");
      if (j === 0) {
        const sw = el("span", undefined, "swatch");
        sw.style.background = m.colour;
        td.prepend(sw);
      }
      if (name === "status") td.classList.add("status-" + m.status);
      td.dataset.value = v === null || v === undefined ? "" : String(v);
      tr.appendChild(td);
    });
    tr.addEventListener("click", () => select(m.id, true));
    table.tBodies[0].appendChild(tr);
  });
  function sortBy(j, th) {
    const asc = th.getAttribute("aria-sort") !== "ascending";
    table.tHead.querySelectorAll("th").forEach((h) => h.setAttribute("aria-sort", "none"));
    th.setAttribute("aria-sort", asc ? "ascending" : "descending");
    const num = COLS[j][2];
    const rows = Array.from(table.tBodies[0].rows);
    rows.sort((a, b) => {
      const va = a.cells[j].dataset.value, vb = b.cells[j].dataset.value;
      if (va === "" || vb === "") return va === vb ? 0 : va === "" ? 1 : -1;  // blanks last
      const c = num ? Number(va) - Number(vb) : va.localeCompare(vb);
      return asc ? c : -c;
    });
    rows.forEach((r) => table.tBodies[0].appendChild(r));
  }
  const first = D.missions.find((m) => lines[m.id]);
  if (first) select(first.id, false);
  document.body.dataset.ready = "1";
})();
