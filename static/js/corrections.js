// Corrections of the thread masks in the 2D images: a tool bar (inspect, remove a piece, add a
// piece, erase and paint brushes, brush size, undo, redo, clear, export), clicks and strokes
// on both canvases. Each action is one POST; the server stores it, runs the frame again and
// the page follows its session's state as for any run (the overlays "added by you" and
// "removed by you" show what changed).
import { $, S, api, enc, fill, h, onState } from "./core.js";
import { drawImages } from "./images.js";

const TOOLS = [
  ["inspect", "Inspect", "click a pixel of the left image to inspect it"],
  ["remove", "Remove piece", "click a segmented piece (e.g. a vessel) to remove it"],
  ["add", "Add piece", "click the thread where it was missed to add the piece there"],
  ["erase", "Erase", "drag a brush over the mask to erase it"],
  ["paint", "Paint", "drag a brush to mark thread pixels by hand"],
];
S.tool = "inspect";
S.corrections = null;  // the shown frame's {corrections, can_undo, can_redo}
let busy = false;

function buildBar() {
  const tools = TOOLS.map(([key, label, title]) => h("button", {
    class: key === S.tool ? "tool on" : "tool", title, dataset: { tool: key },
    onclick: () => setTool(key),
  }, label));
  fill("#correct-tools",
    h("span", { class: "hint" }, "Mask:"), ...tools,
    h("label", { title: "Remove piece: its partner in the other view (same rows) goes too" },
      h("input", { id: "corr-stereo", type: "checkbox", checked: true }), " both views"),
    h("label", { title: "brush radius, px" }, " radius ",
      h("input", { id: "brush-radius", type: "number", min: "1", max: "200", step: "1", value: "6" })),
    h("button", { id: "corr-undo", title: "undo the last correction (Ctrl+Z)", onclick: () => action("undo") }, "Undo"),
    h("button", { id: "corr-redo", title: "redo (Ctrl+Y)", onclick: () => action("redo") }, "Redo"),
    h("button", { id: "corr-clear", title: "back to the segmenter's masks (undoable)", onclick: () => action("clear") }, "Clear"),
    h("a", { id: "mask-export", href: "#", download: "", title: "the masks the run uses, left | right, as PNG" }, "export mask"),
    h("span", { id: "corr-msg", class: "hint" }));
  showSummary();
}

function setTool(key) {
  S.tool = key;
  for (const b of document.querySelectorAll("#correct-tools .tool")) b.classList.toggle("on", b.dataset.tool === key);
  for (const side of ["left", "right"]) $(`#img-${side}`).classList.toggle("correcting", key !== "inspect");
}

function message(text) { $("#corr-msg").textContent = text || ""; }

function showSummary() {
  const c = S.corrections;
  const frame = S.frameId;
  $("#corr-undo").disabled = !c || !c.can_undo || busy;
  $("#corr-redo").disabled = !c || !c.can_redo || busy;
  $("#corr-clear").disabled = !c || !c.corrections.length || busy;
  const link = $("#mask-export");
  if (frame) {
    link.href = `/api/frames/${enc(frame)}/mask.png?view=both&session=${encodeURIComponent(S.session || "")}`;
    link.setAttribute("download", `${frame.split("/").pop()}_mask.png`);
  }
  $("#correct-tools").dataset.count = c ? String(c.corrections.length) : "";
  $("#correct-tools").dataset.busy = busy ? "1" : "";
}

async function loadCorrections(frameId) {
  try {
    const c = await api("GET", `/api/frames/${enc(frameId)}/corrections`);
    if (frameId === S.frameId) { S.corrections = c; showSummary(); }
  } catch (e) { message(e.message); }
}

async function send(method, path, body) {
  const frameId = S.frameId;
  if (!frameId || busy) return;
  busy = true; showSummary(); message("applying...");
  try {
    const r = await api(method, `/api/frames/${enc(frameId)}/${path}`, Object.assign({ session: S.session, wait: true }, body || {}));
    if (frameId === S.frameId) S.corrections = r;
    const n = r.corrections.length;
    message(`${n} correction${n === 1 ? "" : "s"} applied`);
  } catch (e) { message(`not applied: ${e.message}`); }
  busy = false; showSummary();
  drawImages();  // the stroke's preview gives way to the overlays
}

function action(kind) { return send("POST", `corrections/${kind}`); }

// --- clicks and strokes on the images ---------------------------------------------------

function pixelOf(canvas, ev) {
  const r = canvas.getBoundingClientRect();
  return [Math.floor((ev.clientX - r.left) * canvas.width / r.width), Math.floor((ev.clientY - r.top) * canvas.height / r.height)];
}

function radius() {
  const v = Number($("#brush-radius").value);
  return Number.isFinite(v) && v > 0 ? v : 6;
}

let stroke = null;  // {side, points} while a brush is dragged

function preview(canvas, p, q) {
  const ctx = canvas.getContext("2d");
  ctx.strokeStyle = S.tool === "erase" ? "rgba(255,70,70,0.6)" : "rgba(60,230,110,0.6)";
  ctx.lineCap = "round"; ctx.lineWidth = 2 * radius();
  ctx.beginPath(); ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]); ctx.stroke();
}

for (const side of ["left", "right"]) {
  const canvas = $(`#img-${side}`);
  canvas.addEventListener("mousedown", (ev) => {
    if (S.tool !== "erase" && S.tool !== "paint") return;
    ev.preventDefault();
    const p = pixelOf(canvas, ev);
    stroke = { side, points: [p] };
    preview(canvas, p, p);
  });
  canvas.addEventListener("mousemove", (ev) => {
    if (!stroke || stroke.side !== side) return;
    const p = pixelOf(canvas, ev), last = stroke.points[stroke.points.length - 1];
    if (p[0] === last[0] && p[1] === last[1]) return;
    stroke.points.push(p);
    preview(canvas, last, p);
  });
  canvas.addEventListener("click", (ev) => {
    if (S.tool !== "remove" && S.tool !== "add") return;
    const body = { op: S.tool, view: side, points: [pixelOf(canvas, ev)] };
    if (S.tool === "remove") body.stereo = $("#corr-stereo").checked;
    send("POST", "corrections", body);
  });
}
window.addEventListener("mouseup", () => {
  if (!stroke) return;
  const s = stroke; stroke = null;
  send("POST", "corrections", { op: S.tool, view: s.side, points: s.points.slice(0, 5000), radius: radius() });
});
document.addEventListener("keydown", (ev) => {
  if (ev.target.closest("input, textarea, select") || !(ev.ctrlKey || ev.metaKey)) return;
  const key = ev.key.toLowerCase();
  if (key === "z" && !ev.shiftKey) { ev.preventDefault(); action("undo"); }
  else if (key === "y" || (key === "z" && ev.shiftKey)) { ev.preventDefault(); action("redo"); }
});

let shownFrame = null;
onState((st) => {
  if (st.frame_id && st.frame_id !== shownFrame) { shownFrame = st.frame_id; S.corrections = null; showSummary(); loadCorrections(st.frame_id); }
});
buildBar();
setTool("inspect");
