// Images panel: the rectified pair with the stage overlays, and the pixel inspector's E(d).
import { $, S, api, enc, fill, fmt, h, onState } from "./core.js";

export function loadImages(id) {
  if (S.imageFrame === id) return;
  S.imageFrame = id;
  for (const side of ["left", "right"]) {
    const img = new Image();
    img.onload = () => { if (S.imageFrame === id) { S.images[side] = img; drawImages(); } };
    img.src = `/api/frames/${enc(id)}/images/${side}`;
  }
  S.images = {};
}

// --- 2D overlays -----------------------------------------------------------------------------

let overlayBusy = false, overlayAt = 0, overlayTimer = null, busySince = 0;
const OVERLAY_EVERY_MS = 400;  // while a run is going on, overlays follow at this pace (a run
// shorter than this, e.g. a slider move, gets one overlay: its last)
async function refreshOverlay() {
  if (overlayBusy || S.overlayVersion === S.version) return;
  const busy = Boolean(S.state && S.state.busy);
  if (busy && !busySince) busySince = Date.now();
  if (!busy) busySince = 0;
  const wait = OVERLAY_EVERY_MS - (Date.now() - Math.max(overlayAt, busySince));
  if (busy && wait > 0) {
    if (!overlayTimer) overlayTimer = setTimeout(() => { overlayTimer = null; refreshOverlay(); }, wait);
    return;
  }
  overlayBusy = true;
  overlayAt = Date.now();
  try {
    const v = S.version;
    const ov = await getOverlay();
    if (v > S.overlayVersion) takeOverlay(ov, v);  // else a newer state brought its own
  } catch (e) { /* the next state refreshes it */ }
  overlayBusy = false;
  if (S.overlayVersion !== S.version) refreshOverlay();
}

// The overlays the page shows and does not hold (the route of a state's answer, asked alone).
function getOverlay() {
  return api("GET", `/api/sessions/${S.session}/overlay?known=${knownOverlays()}&keys=${shownOverlays()}`);
}

// The keys of the overlays the page shows: the server builds and sends only those, and names
// the others (`_later`); one that is turned on (or revealed by the stepper) is fetched then.
export function shownOverlays() {
  return S.info ? S.info.overlays.filter(overlayOn).map((o) => o.key).join(",") : "";
}

let laterBusy = false;
async function fetchShownLater() {
  const ov = S.overlay;
  if (laterBusy || !ov || !ov._later || !S.info.overlays.some((o) => overlayOn(o) && ov._later.includes(o.key))) return;
  laterBusy = true;
  try {
    const v = S.overlayVersion;
    const got = await getOverlay();
    if (S.overlayVersion === v) takeOverlay(got, v);  // else a newer state brought its own
  } catch (e) { /* the next state refreshes it */ }
  laterBusy = false;
}

// The tags of the overlay payloads the page holds: the server leaves those out of its answer.
export function knownOverlays() {
  const old = S.overlay && S.overlay._tags ? S.overlay : null;
  return old ? Object.keys(old._tags).filter((k) => k in old).map((k) => old._tags[k]).join(",") : "";
}

// An overlay answer (from /overlay or with a finished run's state) of session version `v`:
// the payloads left out are the ones held; an unchanged overlay is not drawn again.
function takeOverlay(ov, v) {
  const old = S.overlay && S.overlay._tags ? S.overlay : null;
  let same = Boolean(old) && old.frame_id === ov.frame_id;
  for (const [k, tag] of Object.entries(ov._tags || {})) {
    if (!(k in ov) && old && old._tags[k] === tag) ov[k] = old[k];
    else same = false;
  }
  if (same && Object.keys(old._tags).length !== Object.keys(ov._tags || {}).length) same = false;
  S.overlay = ov;
  S.overlayVersion = v;
  if (!same) drawImages();
  S.overlayShown = { version: ov.version, at: Date.now() };  // for scripts/bench_latency.py
  fetchShownLater();  // an overlay shown since the request (the stepper's reveal)
}

// The toggles come from /api/info (the server's overlay registry), never from a copy here.
export function buildOverlayToggles() {
  const boxes = S.info.overlays.map((o) => h("label", {},
    h("input", { type: "checkbox", dataset: { ov: o.key }, checked: o.on, onchange: () => { drawImages(); fetchShownLater(); } }),
    ` ${o.label} `, o.count ? h("span", { class: "count", dataset: { count: o.key } }) : null));
  fill("#overlay-toggles", boxes);
}

function overlayOn(o) {
  const box = document.querySelector(`[data-ov="${CSS.escape(o.key)}"]`);
  if (box && box.checked) return true;
  // the stepper showing exactly the overlay's stage shows it whatever the toggle
  return Boolean(o.reveal && S.state && S.info.stages[S.state.reveal - 1] === o.reveal);
}

// One drawing routine per overlay kind (app/views/registry.OverlayKind).
const DRAW = {
  pixels(ctx, o, flat, meta) {  // step x step blocks when the server decimated the list
    const s = (meta && meta.step) || 1;
    ctx.fillStyle = o.color;
    for (let i = 0; i < flat.length; i += 2) ctx.fillRect(flat[i], flat[i + 1], s, s);
  },
  circles(ctx, o, pts) {
    ctx.strokeStyle = o.color; ctx.lineWidth = 1.5;
    for (const k of pts) { ctx.beginPath(); ctx.arc(k[0], k[1], 3, 0, 2 * Math.PI); ctx.stroke(); }
  },
  squares(ctx, o, pts) {
    for (const q of pts) {
      ctx.fillStyle = q[2] === false && o.color2 ? o.color2 : o.color;
      ctx.fillRect(q[0] - 1.5, q[1] - 1.5, 3, 3);
    }
  },
  polyline(ctx, o, line) {
    const pts = line.points;
    if (!pts || pts.length < 2) return;
    ctx.lineWidth = 1.5; ctx.setLineDash(o.dash ? [4, 3] : []);
    if (line.colors) {  // one colour per segment (e.g. confidence along the curve)
      for (let i = 0; i + 1 < pts.length; i++) {
        ctx.strokeStyle = line.colors[i] || o.color;
        ctx.beginPath(); ctx.moveTo(pts[i][0], pts[i][1]); ctx.lineTo(pts[i + 1][0], pts[i + 1][1]); ctx.stroke();
      }
    } else {
      ctx.strokeStyle = o.color; ctx.beginPath(); ctx.moveTo(pts[0][0], pts[0][1]);
      for (const q of pts) ctx.lineTo(q[0], q[1]);
      ctx.stroke();
    }
    ctx.setLineDash([]);
  },
  segments(ctx, o, seg) {  // separate segments, optional colour per segment and text labels
    ctx.lineWidth = 1.5; ctx.setLineDash(o.dash ? [4, 3] : []);
    (seg.segments || []).forEach((q, i) => {
      ctx.strokeStyle = (seg.colors && seg.colors[i]) || o.color;
      ctx.beginPath(); ctx.moveTo(q[0], q[1]); ctx.lineTo(q[2], q[3]); ctx.stroke();
    });
    ctx.setLineDash([]);
    ctx.font = "10px sans-serif"; ctx.lineWidth = 3; ctx.strokeStyle = "rgba(0,0,0,0.7)";
    for (const [x, y, text, color] of seg.labels || []) {  // canvas text: never parsed as HTML
      ctx.strokeText(String(text), x + 2, y - 2);
      ctx.fillStyle = color || o.color; ctx.fillText(String(text), x + 2, y - 2);
    }
  },
};

const pixelMeta = (ov, key, side) => ov._pixels && ov._pixels[key] && ov._pixels[key][side];
const countOf = (o, payload, meta) => (o.kind === "pixels" ? (meta ? meta.count : payload.length / 2) : o.kind === "polyline" ? payload.points.length : o.kind === "segments" ? (payload.labels || []).length : payload.length);

export function drawImages() {
  const t0 = performance.now();
  const ov = S.overlay && S.overlay.frame_id === S.frameId ? S.overlay : {};
  const overlays = S.info ? S.info.overlays : [];
  for (const o of overlays) {
    const badge = document.querySelector(`[data-count="${CSS.escape(o.key)}"]`);
    if (badge) badge.textContent = ov[o.key] && ov[o.key].left ? `(${countOf(o, ov[o.key].left, pixelMeta(ov, o.key, "left"))})` : "";
  }
  for (const side of ["left", "right"]) {
    const canvas = $(`#img-${side}`);
    const img = S.images[side];
    const ctx = canvas.getContext("2d");
    if (!img) { ctx.clearRect(0, 0, canvas.width, canvas.height); continue; }
    if (canvas.width !== img.width) { canvas.width = img.width; canvas.height = img.height; }
    ctx.drawImage(img, 0, 0);
    for (const o of overlays) {
      const payload = ov[o.key] && ov[o.key][side];
      if (payload && overlayOn(o)) DRAW[o.kind](ctx, o, payload, pixelMeta(ov, o.key, side));
    }
    if (side === "left" && S.pixel && S.pixel.segmented) {  // crosshair on the inspected pixel
      const { x, y } = S.pixel;
      ctx.strokeStyle = "#00ff66"; ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.moveTo(x - 9, y); ctx.lineTo(x - 3, y); ctx.moveTo(x + 3, y); ctx.lineTo(x + 9, y);
      ctx.moveTo(x, y - 9); ctx.lineTo(x, y - 3); ctx.moveTo(x, y + 3); ctx.lineTo(x, y + 9);
      ctx.stroke();
    }
    const sp = ov.spline && ov.spline[side];
    $(`#err-${side}`).textContent = sp && sp.mean_px !== undefined ? `reprojection mean ${fmt(sp.mean_px, 2)} px, max ${fmt(sp.max_px, 2)} px, coverage ${fmt(sp.coverage, 2)}` : "";
  }
  S.drawMs = performance.now() - t0;  // the last drawing's ms (scripts/bench_latency.py)
}

// --- pixel inspector -------------------------------------------------------------------------

async function inspect(x, y) {
  try {
    const info = await api("GET", `/api/sessions/${S.session}/pixel?x=${x}&y=${y}`);
    S.pixel = Object.assign(info, { version: S.version });
  } catch (e) { S.pixel = null; $("#pixel-info").textContent = e.message; }
  drawEnergy();
  drawImages();
}

function drawEnergy() {
  const canvas = $("#energy");
  const ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height;
  ctx.clearRect(0, 0, W, H);
  const p = S.pixel;
  canvas.dataset.pixel = p && p.segmented ? `${p.x},${p.y}` : "";
  if (!p) { $("#pixel-info").textContent = "Click a pixel of the left image, or a point of the 3D cloud."; return; }
  if (!p.segmented) { $("#pixel-info").textContent = `(${p.x}, ${p.y}) is not a segmented thread pixel.`; return; }
  // log axis: E_min and E_next are often orders of magnitude apart
  const E = p.energy.map((v) => (v === null || v < 0 ? NaN : Math.log10(1 + v)));
  const finite = E.filter(Number.isFinite);
  const lo = Math.min(...finite), hi = Math.max(...finite);
  const pad = 22, sx = (d) => pad + (d / (E.length - 1)) * (W - pad - 6);
  const sy = (e) => H - 16 - ((e - lo) / (hi - lo || 1)) * (H - 26);
  ctx.strokeStyle = "#2d313b"; ctx.strokeRect(pad, 4, W - pad - 6, H - 20);
  ctx.fillStyle = "#8d94a3"; ctx.font = "10px sans-serif";
  ctx.fillText("0", pad - 3, H - 4); ctx.fillText(`α=${E.length - 1}`, W - 34, H - 4); ctx.fillText("log E(d)", 2, 12);
  ctx.strokeStyle = "#e3e6ec"; ctx.lineWidth = 1.2; ctx.beginPath();
  let started = false;
  E.forEach((e, d) => { if (!Number.isFinite(e)) return; if (!started) { ctx.moveTo(sx(d), sy(e)); started = true; } else ctx.lineTo(sx(d), sy(e)); });
  ctx.stroke();
  const mark = (d, color, label, row) => {
    ctx.strokeStyle = color; ctx.setLineDash([3, 2]); ctx.beginPath(); ctx.moveTo(sx(d), 4); ctx.lineTo(sx(d), H - 16); ctx.stroke(); ctx.setLineDash([]);
    ctx.fillStyle = color; ctx.fillText(label, Math.min(sx(d) + 3, W - 52), 16 + 12 * row);
  };
  mark(p.d_min, "#3ccf73", `d_min ${p.d_min}`, 0);
  mark(p.d_next, "#ff5c5c", `d_next ${p.d_next}`, 1);
  const rel = p.R === undefined ? "" : `, R ${fmt(p.R)} (${p.reliable ? "reliable" : "not reliable"}, threshold ${p.threshold})`;
  const depth = p.depth === null ? "no depth" : `depth ${fmt(p.depth, 3)} ${S.state && S.state.unit ? S.state.unit : ""}`;
  $("#pixel-info").textContent = `pixel (${p.x}, ${p.y}): E_min ${fmt(p.E_min, 1)}, E_next ${fmt(p.E_next, 1)}${rel}, ${depth}`;
}

onState((st) => {
  if (st.frame_id !== S.shownFrame) { S.shownFrame = st.frame_id; S.pixel = null; drawEnergy(); }
  if (st.frame_id) loadImages(st.frame_id);
  if (st.inspect && st.inspect.segmented && (!S.pixel || S.pixel.x !== st.inspect.x || S.pixel.y !== st.inspect.y || S.pixel.version !== st.version)) {
    S.pixel = Object.assign({}, st.inspect, { version: st.version });
    drawEnergy();
  }
  if (st.overlay) takeOverlay(st.overlay, st.version);  // a finished run's
  else refreshOverlay();
});

$("#img-left").addEventListener("click", (ev) => {
  if (S.tool && S.tool !== "inspect") return;  // a correction tool (corrections.js) has the click
  const c = ev.currentTarget, r = c.getBoundingClientRect();
  const x = Math.floor((ev.clientX - r.left) * c.width / r.width);
  const y = Math.floor((ev.clientY - r.top) * c.height / r.height);
  inspect(x, y);
});
