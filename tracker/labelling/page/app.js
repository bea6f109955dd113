// keyshape label: drag landmark points on each chosen frame and save them as .pts files.
"use strict";
(function () {
  const COLOURS = { brow: "#ffd24d", eye: "#4dff88", pupil: "#ff4d4d", lip: "#4dc3ff",
                    jaw: "#ffffff", nose: "#ff9f4d", mouth: "#4dc3ff" };
  const canvas = document.getElementById("view");
  const ctx = canvas.getContext("2d");
  const statusEl = document.getElementById("status");
  const S = { scheme: null, frames: [], index: 0, points: null, image: null, scale: 1,
              drag: -1, dirty: false, undo: [], saves: 0 };

  function colour(name) {
    for (const k in COLOURS) if (name.startsWith(k)) return COLOURS[k];
    return "#ffffff";
  }
  function setStatus(text, cls) { statusEl.textContent = text; statusEl.className = cls || ""; }

  function fit() {
    if (!S.image) return;
    const w = S.image.naturalWidth, h = S.image.naturalHeight;
    const maxW = Math.max(200, window.innerWidth - 40), maxH = Math.max(200, window.innerHeight - 120);
    S.scale = Math.min(maxW / w, maxH / h, 4);
    canvas.width = Math.round(w * S.scale);
    canvas.height = Math.round(h * S.scale);
    draw();
  }

  function draw() {
    if (!S.image || !S.points) return;
    ctx.drawImage(S.image, 0, 0, canvas.width, canvas.height);
    const k = S.scale, P = S.points;
    for (const [name, idx] of Object.entries(S.scheme.contours)) {
      ctx.strokeStyle = ctx.fillStyle = colour(name);
      ctx.lineWidth = 1;
      const ok = idx.every(i => P[i] && P[i][0] !== null);
      if (idx.length > 1 && ok) {
        ctx.beginPath();
        idx.forEach((i, j) => j ? ctx.lineTo(P[i][0] * k, P[i][1] * k) : ctx.moveTo(P[i][0] * k, P[i][1] * k));
        if (S.scheme.closed[name]) ctx.closePath();
        ctx.stroke();
      }
      for (const i of idx) {
        if (!P[i] || P[i][0] === null) continue;
        ctx.beginPath();
        ctx.arc(P[i][0] * k, P[i][1] * k, i === S.drag ? 5 : 3, 0, 2 * Math.PI);
        if (idx.length === 1) ctx.stroke(); else ctx.fill();
      }
    }
  }

  function screenPos(i) {  // page coordinates of point i (used by the browser test)
    const r = canvas.getBoundingClientRect();
    return { x: r.left + S.points[i][0] * S.scale, y: r.top + S.points[i][1] * S.scale };
  }

  function nearest(ev) {
    const r = canvas.getBoundingClientRect();
    const x = (ev.clientX - r.left) / S.scale, y = (ev.clientY - r.top) / S.scale;
    let best = -1, bestD = (10 / S.scale) ** 2;
    S.points.forEach((p, i) => {
      if (!p || p[0] === null) return;
      const d = (p[0] - x) ** 2 + (p[1] - y) ** 2;
      if (d < bestD) { bestD = d; best = i; }
    });
    return best;
  }

  canvas.addEventListener("mousedown", ev => {
    if (!S.points) return;
    S.drag = nearest(ev);
    if (S.drag >= 0) { S.undo.push([S.drag, S.points[S.drag].slice()]); canvas.classList.add("dragging"); draw(); }
  });
  window.addEventListener("mousemove", ev => {
    if (S.drag < 0) return;
    const r = canvas.getBoundingClientRect();
    const w = S.image.naturalWidth, h = S.image.naturalHeight;
    S.points[S.drag] = [Math.min(Math.max((ev.clientX - r.left) / S.scale, 0), w - 1),
                        Math.min(Math.max((ev.clientY - r.top) / S.scale, 0), h - 1)];
    if (!S.dirty) { S.dirty = true; setStatus("unsaved changes", "dirty"); }
    draw();
  });
  window.addEventListener("mouseup", () => {
    if (S.drag >= 0) { S.drag = -1; canvas.classList.remove("dragging"); draw(); }
  });

  async function api(path, opts) {
    const r = await fetch(path, opts);
    const body = await r.json().catch(() => ({}));
    if (!r.ok) throw new Error(body.error || r.statusText);
    return body;
  }

  async function save() {
    if (!S.points) return;
    if (S.points.some(p => !p || p[0] === null)) { setStatus("some points are missing: place them first", "error"); return; }
    const name = S.frames[S.index] + ".pts";
    try {
      await api("/api/points/" + name, { method: "PUT", headers: { "Content-Type": "application/json" },
                                         body: JSON.stringify({ points: S.points }) });
      S.dirty = false; S.saves += 1;
      setStatus("saved " + name);
    } catch (e) { setStatus("save failed: " + e.message, "error"); throw e; }
  }

  async function show(index) {
    if (S.dirty && document.getElementById("autosave").checked) await save();
    S.index = Math.min(Math.max(index, 0), S.frames.length - 1);
    const f = S.frames[S.index];
    document.getElementById("where").textContent =
      "frame " + Number(f) + " (" + (S.index + 1) + " of " + S.frames.length + ")";
    const [pts, img] = await Promise.all([
      api("/api/points/" + f + ".pts"),
      new Promise((ok, fail) => { const im = new Image(); im.onload = () => ok(im); im.onerror = fail;
                                  im.src = "/frames/" + f + ".png"; })]);
    S.points = pts.points; S.image = img; S.dirty = false; S.undo = [];
    setStatus("");
    fit();
    canvas.dataset.frame = f;  // lets tests wait for a frame to be shown
  }

  document.getElementById("prev").onclick = () => show(S.index - 1);
  document.getElementById("next").onclick = () => show(S.index + 1);
  document.getElementById("save").onclick = () => save();
  window.addEventListener("keydown", ev => {
    if (ev.key === "ArrowLeft" || ev.key === "p") show(S.index - 1);
    else if (ev.key === "ArrowRight" || ev.key === "n") show(S.index + 1);
    else if (ev.key === "s" || (ev.key === "S" && ev.ctrlKey) || (ev.key === "s" && ev.ctrlKey)) { ev.preventDefault(); save(); }
    else if (ev.key === "z" && S.undo.length) { const [i, p] = S.undo.pop(); S.points[i] = p; S.dirty = true; draw(); }
  });
  window.addEventListener("resize", fit);
  window.addEventListener("beforeunload", ev => { if (S.dirty) { ev.preventDefault(); ev.returnValue = ""; } });

  window.keyshapeLabel = { state: S, screenPos, save, show };
  api("/api/session").then(s => { S.scheme = s.scheme; S.frames = s.frames; return show(0); })
    .catch(e => setStatus("cannot load: " + e.message, "error"));
})();
