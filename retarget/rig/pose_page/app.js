"use strict";
// Pose-correction page: one key at a time; a slider change is PUT to /api/poses/<key> (saved at once).
let lib = null, key = null, timer = null, version = 0;
const $ = (id) => document.getElementById(id);
const status = (text, error) => { $("status").textContent = text; $("status").className = error ? "error" : ""; };
const regionOf = (k) => Object.keys(lib.regions).find((r) => k in lib.regions[r].keys);

function drawActor() {
  const svg = $("actor"), a = lib.actor[key];
  svg.innerHTML = "";
  if (!a) { svg.innerHTML = '<text x="10" y="20" fill="#888">no KEYS.json: actor not shown</text>'; return; }
  const all = a.rest.concat(a.shape);
  const xs = all.map((p) => p[0]), ys = all.map((p) => p[1]);
  const x0 = Math.min(...xs), y0 = Math.min(...ys);
  const s = 280 / Math.max(Math.max(...xs) - x0, Math.max(...ys) - y0, 1e-9);
  const pt = (p) => `${20 + (p[0] - x0) * s},${20 + (p[1] - y0) * s}`;
  for (const [pts, colour] of [[a.rest, "#888"], [a.shape, "#f93"]]) {
    a.lines.forEach((line, i) => {
      const el = document.createElementNS("http://www.w3.org/2000/svg", a.closed[i] ? "polygon" : "polyline");
      el.setAttribute("points", line.map((j) => pt(pts[j])).join(" "));
      el.setAttribute("fill", "none"); el.setAttribute("stroke", colour); el.setAttribute("stroke-width", "2");
      svg.appendChild(el);
    });
  }
}

function drawRig() {
  if (lib.render) $("rig").src = `/api/render/${encodeURIComponent(key)}.png?v=${++version}`;
}

function pose() { return lib.regions[regionOf(key)].keys[key]; }

function drawSliders() {
  const box = $("sliders"), [lo, hi] = lib.range, p = pose();
  box.innerHTML = "";
  for (const s of lib.regions[regionOf(key)].shapes) {
    const name = document.createElement("label"), input = document.createElement("input"),
      value = document.createElement("span");
    name.textContent = s; name.className = p[s] ? "on" : "";
    input.type = "range"; input.min = lo; input.max = hi; input.step = (hi - lo) / 200; input.value = p[s] || 0;
    value.textContent = (p[s] || 0).toFixed(2);
    input.addEventListener("input", () => {
      const v = parseFloat(input.value);
      if (v) p[s] = v; else delete p[s];
      value.textContent = v.toFixed(2); name.className = v ? "on" : "";
      save();
    });
    box.append(name, input, value);
  }
}

function save() {
  clearTimeout(timer);
  status("changed…");
  timer = setTimeout(async () => {
    const k = key;
    const r = await fetch(`/api/poses/${encodeURIComponent(k)}`, {
      method: "PUT", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ pose: pose() }) });
    const body = await r.json();
    if (r.ok) { status(`saved ${k}`); if (k === key) drawRig(); } else status(body.error, true);
  }, 250);
}

function show(k) { key = k; $("key").value = k; drawActor(); drawRig(); drawSliders(); status(""); }

async function start() {
  const r = await fetch("/api/library");
  lib = await r.json();
  $("file").textContent = lib.file;
  const sel = $("key");
  for (const [region, reg] of Object.entries(lib.regions)) {
    const group = document.createElement("optgroup"); group.label = region;
    for (const k of Object.keys(reg.keys)) {
      const o = document.createElement("option"); o.value = o.textContent = k; group.appendChild(o);
    }
    sel.appendChild(group);
  }
  sel.addEventListener("change", () => show(sel.value));
  $("zero").addEventListener("click", () => {
    const p = pose(); for (const s of Object.keys(p)) delete p[s]; drawSliders(); save();
  });
  const first = Object.values(lib.regions).map((reg) => Object.keys(reg.keys)).flat()[0];
  if (first) show(first); else status("the library has no keys", true);
}
start().catch((e) => status(String(e), true));
