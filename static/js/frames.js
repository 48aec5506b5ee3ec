// Frames panel: the frames of the data folder, their status and rating; n / p to step.
import { $, S, api, enc, fill, h, onState, showError } from "./core.js";

export async function loadFrames() {
  S.frames = await api("GET", "/api/frames");
  renderFrames();
}

// The entry of a frame id: a still frame, or the sequence whose frame "<sequence id>@k" it is.
export function entryOf(id) {
  return S.frames.find((f) => f.id === id || (f.kind === "sequence" && id && id.startsWith(`${f.id}@`)));
}

export function renderFrames() {
  const current = entryOf(S.frameId);
  fill("#frames tbody", S.frames.map((f) => h("tr",
    { dataset: { id: f.id }, class: f === current ? "selected" : "",
      onclick: () => selectFrame(f.kind === "sequence" ? (f === current ? S.frameId : `${f.id}@0`) : f.id) },
    h("td", { title: f.id }, f.name),
    h("td", { title: f.kind === "sequence" ? `${f.source} sequence` : "" },
      f.kind === "sequence" ? `seq ${f.count ?? "?"}` : (f.kind === "simulated" ? "sim" : "real")),
    h("td", { class: `st-${f.status ? f.status : "none"}` }, f.status || "–"),
    h("td", { class: "rating" }, f.rating ? "★".repeat(f.rating) : ""),
  )));
}

export async function selectFrame(id) {
  if (!id) return;
  S.frameId = id;
  renderFrames();
  for (const fn of S.frameHooks || []) fn(id);
  try {
    await api("POST", `/api/frames/${enc(id)}/run`, { session: S.session, wait: false });
  } catch (e) { showError(e.message); }
}

export function stepFrame(delta) {
  const i = S.frames.indexOf(entryOf(S.frameId));
  const j = Math.min(S.frames.length - 1, Math.max(0, i + delta));
  if (j !== i) selectFrame(S.frames[j].kind === "sequence" ? `${S.frames[j].id}@0` : S.frames[j].id);
}

export function setFrameField(frameId, key, value) {
  const f = S.frames.find((x) => x.id === frameId);
  if (f && f[key] !== value) { f[key] = value; renderFrames(); }
}

onState((st) => {
  const f = S.frames.find((x) => x.id === st.frame_id);
  if (f && !st.busy && st.status !== "pending") {
    const status = st.stages.every((s) => !s.revealed || s.status !== "pending") ? st.status : f.status;
    setFrameField(f.id, "status", status);
  }
});

document.addEventListener("keydown", (ev) => {
  if (ev.target.closest("input, textarea, select")) return;
  if (ev.key === "n") stepFrame(1);
  else if (ev.key === "p") stepFrame(-1);
});
