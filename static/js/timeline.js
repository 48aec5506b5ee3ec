// Timeline panel: a sequence's frame slider, play/pause, and per-frame status, length,
// confidence and time plotted along the timeline (click to jump). The slider selects the frame
// "<sequence>@k" in the session, so every stage layer follows it; the plot's rows and the
// tracked / single-frame curves come from /api/sequences/<id>/timeline (computed in the
// background on the server, with tracking unless the box is unticked).
import { $, S, api, enc, fmt, onState, showError } from "./core.js";
import { selectFrame } from "./frames.js";

const T = { seq: null, count: 0, k: 0, rows: [], done: false, tracking: true, key: null,
  curves: null, curvesFor: null, playing: false, polling: false, lastStep: 0 };
S.timeline = T;  // for the browser tests

const PLAY_MIN_MS = 250;  // at most 4 frames a second while playing (each frame runs every stage)
const POLL_MS = 600;  // timeline progress is fetched at this pace until done
const STATUS_RGB = { ok: "#3ccf73", suspect: "#f0b429", failed: "#ff5c5c", predicted: "#5aa0ff", lost: "#ff5c5c", off: "#8d94a3" };

export function sequenceOf(id) {
  if (!id) return null;
  const at = id.lastIndexOf("@");
  if (at < 0) return null;
  const seq = S.frames.find((f) => f.kind === "sequence" && f.id === id.slice(0, at));
  return seq ? { seq, k: Number(id.slice(at + 1)) } : null;
}

function show(found) {
  $("#timeline").hidden = !found;
  if (!found) { pause(); T.seq = null; return; }
  const { seq, k } = found;
  if (T.seq !== seq.id) {
    T.seq = seq.id; T.count = seq.count || 0; T.rows = []; T.done = false; T.key = null;
    $("#tl-slider").max = String(Math.max(0, T.count - 1));
  }
  T.k = k;
  $("#tl-slider").value = String(k);
  $("#tl-frame").textContent = `${k + 1} / ${T.count || "?"}`;
  ensurePolling();
  if (T.curvesFor !== k) loadCurves();
  drawPlot();
}

function timelineUrl(rest) {
  return `/api/sequences/${enc(T.seq)}/${rest}?session=${S.session}&tracking=${T.tracking}`;
}

async function ensurePolling() {
  const key = `${T.seq}|${T.tracking}|${S.state ? S.state.params_hash : ""}`;
  if (T.key !== key) { T.key = key; T.rows = []; T.done = false; T.curvesFor = null; }
  if (T.polling || T.done || !T.seq) return;
  T.polling = true;
  try {
    while (!T.done && T.key === key) {
      const tl = await api("GET", `${timelineUrl("timeline")}&since=${T.rows.length}`);
      if (T.key !== key) break;
      T.rows = T.rows.concat(tl.rows);
      T.done = tl.done;
      if (tl.count) { T.count = tl.count; $("#tl-slider").max = String(T.count - 1); }
      $("#tl-progress").textContent = tl.error ? `timeline stopped: ${tl.error}`
        : (tl.done ? `${T.rows.length} frames${T.tracking ? ", tracked" : ""}` : `computing ${T.rows.length} / ${T.count || "?"}`);
      drawPlot();
      if (T.curvesFor !== T.k) loadCurves();
      if (!T.done) await new Promise((r) => setTimeout(r, POLL_MS));
    }
  } catch (e) { $("#tl-progress").textContent = e.message; }
  T.polling = false;
  if (!T.done && T.seq && T.key !== key) ensurePolling();
}

async function loadCurves() {
  const k = T.k;
  if (!T.seq || k >= T.rows.length) { T.curves = null; T.curvesFor = null; drawCurves(); return; }
  try {
    const data = await api("GET", timelineUrl(`curves/${k}`));
    if (T.k === k) { T.curves = data.curves; T.curvesFor = k; drawCurves(); }
  } catch (e) { T.curves = null; drawCurves(); }
}

// --- the plot --------------------------------------------------------------------------------

const PAD = { l: 44, r: 8, t: 6, b: 14 };
const LANES = [  // [key, label, share of the height]
  ["status", "status", 0.12], ["length", "length", 0.36], ["confidence", "confidence", 0.24], ["ms", "ms", 0.28],
];

function xOf(k, w) { return PAD.l + (T.count > 1 ? k / (T.count - 1) : 0.5) * (w - PAD.l - PAD.r); }

function series(row, lane) {
  if (lane === "length") return [row.curve_length, row.length];
  if (lane === "confidence") return [row.confidence];
  if (lane === "ms") return [row.ms];
  return [];
}

function drawPlot() {
  const c = $("#tl-plot");
  const w = c.width = c.clientWidth || 720, hgt = c.height = c.clientHeight || 150;
  const ctx = c.getContext("2d");
  ctx.clearRect(0, 0, w, hgt);
  ctx.font = "10px system-ui"; ctx.textBaseline = "middle";
  let y0 = PAD.t;
  const inner = hgt - PAD.t - PAD.b;
  for (const [lane, label, share] of LANES) {
    const lh = inner * share;
    ctx.fillStyle = "#8d94a3"; ctx.fillText(label, 2, y0 + lh / 2);
    ctx.strokeStyle = "#2d313b"; ctx.beginPath(); ctx.moveTo(PAD.l, y0 + lh); ctx.lineTo(w - PAD.r, y0 + lh); ctx.stroke();
    if (lane === "status") {
      for (const r of T.rows) {
        const st = T.tracking ? r.track_status : r.status;
        ctx.fillStyle = STATUS_RGB[st] || "#8d94a3";
        const x = xOf(r.frame, w);
        ctx.fillRect(x - 1.5, y0 + 2, 3, lh - 4);
        if (r.flagged || (T.tracking && r.status !== "ok")) { ctx.fillStyle = STATUS_RGB[r.status] || "#ff5c5c"; ctx.fillRect(x - 1.5, y0 + lh - 3, 3, 3); }
      }
    } else {
      const vals = T.rows.flatMap((r) => series(r, lane)).filter((v) => v !== null && Number.isFinite(v));
      let lo = lane === "confidence" ? 0 : Math.min(...vals), hi = lane === "confidence" ? 1 : Math.max(...vals);
      if (!vals.length) { lo = 0; hi = 1; }
      if (hi - lo < 1e-9) { hi = lo + 1; }
      ctx.fillStyle = "#8d94a3"; ctx.fillText(fmt(hi, hi >= 100 ? 0 : 1), PAD.l - 30, y0 + 6);
      const yOf = (v) => y0 + lh - 2 - (v - lo) / (hi - lo) * (lh - 6);
      const colours = lane === "length" ? ["#35d0ff", "#ff9f40"] : ["#e3e6ec"];
      colours.forEach((col, i) => {
        ctx.strokeStyle = col; ctx.fillStyle = col; ctx.beginPath();
        let on = false;
        for (const r of T.rows) {
          const v = series(r, lane)[i];
          if (v === null || !Number.isFinite(v)) { on = false; continue; }
          const x = xOf(r.frame, w), y = yOf(v);
          if (i === 0) { if (on) ctx.lineTo(x, y); else ctx.moveTo(x, y); on = true; }
          else ctx.fillRect(x - 1, y - 1, 2, 2);  // single-frame length: dots
        }
        if (i === 0) ctx.stroke();
      });
    }
    y0 += lh;
  }
  const x = xOf(T.k, w);
  ctx.strokeStyle = "#ff3ecf"; ctx.lineWidth = 1.5;
  ctx.beginPath(); ctx.moveTo(x, PAD.t); ctx.lineTo(x, hgt - PAD.b); ctx.stroke(); ctx.lineWidth = 1;
  ctx.fillStyle = "#8d94a3"; ctx.textBaseline = "alphabetic";
  ctx.fillText("1", PAD.l, hgt - 2); ctx.fillText(String(T.count), w - PAD.r - 16, hgt - 2);
  const row = T.rows[T.k];
  setLink("#tl-rec-frame", row ? `${timelineUrl("recording.html")}&frame=${T.k}` : null);
  setLink("#tl-rec-seq", T.rows.length ? timelineUrl("recording.html") : null);
  $("#tl-info").textContent = row
    ? `single ${row.status}, tracked ${row.track_status}${row.flagged ? " (flagged)" : ""}; length ${fmt(row.curve_length, 1)}; ${fmt(row.ms, 0)} ms`
      + (row.track_reason ? `; ${row.track_reason}` : "")
      + (row.observed_by === "gate" || row.observed_by === "start"
        ? `; tracker observed the masks ${row.observed_by === "gate" ? "cut to the predicted thread" : "without one piece"} (${row.observed_status}), ${row.tracker_removed_px} px removed`
        : "")
    : "not computed yet";
}

function setLink(sel, url) {
  const a = $(sel);
  if (url) a.setAttribute("href", url); else a.removeAttribute("href");
}

export function frameAt(clientX) {
  const c = $("#tl-plot");
  const rect = c.getBoundingClientRect();
  const w = c.width, px = (clientX - rect.left) * (w / rect.width);
  const t = (px - PAD.l) / (w - PAD.l - PAD.r);
  return Math.round(Math.min(1, Math.max(0, t)) * Math.max(0, T.count - 1));
}

// --- this frame's curves ---------------------------------------------------------------------

function drawCurves() {
  const c = $("#tl-curves"), ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  const curves = T.curves || {};
  const on = (n) => { const b = document.querySelector(`[data-curve="${n}"]`); return !b || b.checked; };
  const all = Object.values(curves).flat();
  if (!all.length) {
    ctx.fillStyle = "#8d94a3"; ctx.font = "11px system-ui";
    ctx.fillText(T.seq ? "curves: not computed yet" : "", 8, 16); return;
  }
  const xs = all.map((p) => p[0]), ys = all.map((p) => p[1]);
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const s = Math.min((c.width - 16) / Math.max(x1 - x0, 1), (c.height - 16) / Math.max(y1 - y0, 1));
  const style = { truth: ["#9aa0aa", [2, 2]], single: ["#ff9f40", [5, 3]], tracked: ["#35d0ff", []] };
  for (const name of ["truth", "single", "tracked"]) {
    const pts = curves[name];
    if (!pts || !on(name)) continue;
    ctx.strokeStyle = style[name][0]; ctx.setLineDash(style[name][1]); ctx.lineWidth = 2; ctx.beginPath();
    pts.forEach(([x, y], i) => { const u = 8 + (x - x0) * s, v = 8 + (y - y0) * s; if (i) ctx.lineTo(u, v); else ctx.moveTo(u, v); });
    ctx.stroke();
  }
  ctx.setLineDash([]); ctx.lineWidth = 1;
}

// --- controls --------------------------------------------------------------------------------

let slideTimer = null;
function goTo(k) {
  if (!T.seq) return;
  k = Math.min(Math.max(0, k), Math.max(0, T.count - 1));
  T.k = k;
  $("#tl-slider").value = String(k);
  $("#tl-frame").textContent = `${k + 1} / ${T.count}`;
  drawPlot();
  loadCurves();
  selectFrame(`${T.seq}@${k}`);
}

function pause() {
  T.playing = false;
  $("#tl-play").textContent = "▶";
}

function tick() {
  if (!T.playing) return;
  const st = S.state;
  const ready = st && !st.busy && st.frame_id === `${T.seq}@${T.k}`;
  if (ready && Date.now() - T.lastStep >= PLAY_MIN_MS) {
    if (T.k >= T.count - 1) { pause(); return; }
    T.lastStep = Date.now();
    goTo(T.k + 1);
  }
  setTimeout(tick, 50);
}

$("#tl-play").addEventListener("click", () => {
  if (T.playing) { pause(); return; }
  if (T.k >= T.count - 1) goTo(0);
  T.playing = true; T.lastStep = 0;
  $("#tl-play").textContent = "⏸";
  tick();
});
$("#tl-slider").addEventListener("input", (ev) => {
  const k = Number(ev.target.value);
  clearTimeout(slideTimer);
  slideTimer = setTimeout(() => goTo(k), 60);  // the session runs the newest frame asked
});
$("#tl-plot").addEventListener("click", (ev) => { pause(); goTo(frameAt(ev.clientX)); });
$("#tl-tracking").addEventListener("change", (ev) => { T.tracking = ev.target.checked; ensurePolling(); });
for (const box of document.querySelectorAll("[data-curve]")) box.addEventListener("change", drawCurves);
document.addEventListener("keydown", (ev) => {
  if (!T.seq || ev.target.closest("input, textarea, select")) return;
  if (ev.key === " ") { ev.preventDefault(); $("#tl-play").click(); }
  else if (ev.key === "ArrowRight") goTo(T.k + 1);
  else if (ev.key === "ArrowLeft") goTo(T.k - 1);
});
window.addEventListener("resize", () => { if (T.seq) drawPlot(); });

onState((st) => {
  try { show(sequenceOf(st.frame_id)); } catch (e) { showError(e.message); }
});
S.frameHooks = (S.frameHooks || []).concat([(id) => { const f = sequenceOf(id); if (f) show(f); }]);
