"use strict";
// Landmark-correction page: pick a point, then click where it should be; PUT /api/points/<i> (saved at once).
const NS = "http://www.w3.org/2000/svg";
let data = null, chosen = null;
const $ = (id) => document.getElementById(id);
const status = (text, error) => { $("status").textContent = text; $("status").className = error ? "error" : ""; };

function label(i) {
  for (const [name, pts] of Object.entries(data.contours)) {
    const k = pts.indexOf(i);
    if (k >= 0) return `point ${i} (${name.replace("_", " ")} ${k}${data.sides[i] ? ", " + data.sides[i][1] : ""})`;
  }
  return `point ${i}`;
}

function draw() {
  data.panels.forEach((_, k) => {
    const svg = $(`svg${k}`), P = data.points[k];
    svg.innerHTML = "";
    for (const [name, pts] of Object.entries(data.contours)) {
      if (pts.length < 2) continue;
      const el = document.createElementNS(NS, data.closed[name] ? "polygon" : "polyline");
      el.setAttribute("points", pts.map((i) => P[i].join(",")).join(" "));
      el.setAttribute("class", "contour");
      svg.appendChild(el);
    }
    P.forEach((p, i) => {
      const c = document.createElementNS(NS, "circle");
      c.setAttribute("cx", p[0]); c.setAttribute("cy", p[1]); c.setAttribute("r", i === chosen ? 5 : 3.5);
      c.setAttribute("class", i === chosen ? "point chosen" : "point");
      const t = document.createElementNS(NS, "title"); t.textContent = label(i); c.appendChild(t);
      c.addEventListener("click", (e) => { e.stopPropagation(); chosen = i; status(`${label(i)}: click where it should be`); draw(); });
      svg.appendChild(c);
    });
  });
}

async function place(k, e) {
  if (chosen === null) { status("click a point first"); return; }
  const svg = $(`svg${k}`), r = svg.getBoundingClientRect();
  const at = [(e.clientX - r.left) * data.size / r.width, (e.clientY - r.top) * data.size / r.height];
  const i = chosen;
  const res = await fetch(`/api/points/${i}`, {
    method: "PUT", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ panel: k, at }) });
  const body = await res.json();
  if (!res.ok) { status(body.error, true); return; }
  data.points = body.points; chosen = null; draw();
  if (body.problem) status(`saved ${label(i)} on vertex ${body.vertex}; but now ${body.problem}`, true);
  else status(`saved ${label(i)} on vertex ${body.vertex}`);
}

async function start() {
  const r = await fetch("/api/landmarks");
  data = await r.json();
  $("file").textContent = `${data.file} (${data.scheme})`;
  const box = $("panels");
  data.panels.forEach((caption, k) => {
    const fig = document.createElement("figure"), wrap = document.createElement("div"), cap = document.createElement("figcaption");
    wrap.className = "stack";
    const img = document.createElement("img");
    img.width = img.height = data.size; img.src = `/api/render/${k}.png`; img.alt = caption;
    const svg = document.createElementNS(NS, "svg");
    svg.id = `svg${k}`; svg.setAttribute("viewBox", `0 0 ${data.size} ${data.size}`);
    svg.setAttribute("width", data.size); svg.setAttribute("height", data.size);
    svg.addEventListener("click", (e) => place(k, e).catch((err) => status(String(err), true)));
    wrap.append(img, svg); cap.textContent = caption; fig.append(wrap, cap); box.appendChild(fig);
  });
  document.addEventListener("keydown", (e) => { if (e.key === "Escape") { chosen = null; status(""); draw(); } });
  draw();
  status("click a point, then where it should be");
}
start().catch((e) => status(String(e), true));
