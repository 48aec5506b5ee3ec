// Rating panel: the paper's 1-5 score with a note. The note box is bound to one frame: a note
// typed on a frame stays with that frame (as a draft) when another frame is shown, and a
// score is only ever saved with the note typed on the frame it rates.
import { $, S, api, enc, onState } from "./core.js";
import { setFrameField } from "./frames.js";

const drafts = new Map();  // frame id -> unsaved note typed on it
const note = $("#rating-note");

function bindNote(frameId, saved) {
  if (note.dataset.frame === frameId) return;
  if (note.dataset.frame && note.dataset.dirty === "1") drafts.set(note.dataset.frame, note.value);
  note.dataset.frame = frameId;
  note.dataset.dirty = drafts.has(frameId) ? "1" : "";
  note.value = drafts.has(frameId) ? drafts.get(frameId) : (saved || "");
}

async function loadRating(frameId) {
  bindNote(frameId, "");
  try {
    const r = await api("GET", `/api/frames/${enc(frameId)}/rating`);
    if (note.dataset.frame === frameId) showRating(r);
  } catch (e) { $("#rating-latest").textContent = e.message; }
}

function showRating(r) {
  const latest = r.latest;
  for (const b of document.querySelectorAll(".star")) {
    b.classList.toggle("on", !!latest && Number(b.dataset.score) <= latest.score);
  }
  $("#rating-latest").textContent = latest
    ? `latest ${latest.score}/5${latest.score < 3 ? " (failure)" : ""}, ${latest.created_at.replace("T", " ").slice(0, 19)} UTC, ` +
      `preset ${latest.preset || "?"}; ${r.history.length} rating${r.history.length > 1 ? "s" : ""} kept`
    : "not rated";
  $("#rating-latest").dataset.score = latest ? latest.score : "";
  if (note.dataset.frame === r.frame_id && note.dataset.dirty !== "1") note.value = latest ? latest.note : "";
  setFrameField(r.frame_id, "rating", latest ? latest.score : null);
}

async function rate(score) {
  const frameId = S.frameId;
  if (!frameId) return;
  bindNote(frameId, "");  // the box shows this frame's note (or draft) before anything is saved
  const text = note.value;
  try {
    const r = await api("PUT", `/api/frames/${enc(frameId)}/rating`, { score, note: text, session: S.session });
    drafts.delete(frameId);
    if (note.dataset.frame === frameId) { note.dataset.dirty = ""; showRating(r); }
  } catch (e) { $("#rating-latest").textContent = `not saved: ${e.message}`; }
}

note.addEventListener("input", () => { note.dataset.dirty = "1"; });
S.frameHooks = (S.frameHooks || []).concat([loadRating]);
onState((st) => { if (st.frame_id && st.frame_id !== note.dataset.frame) loadRating(st.frame_id); });
for (const b of document.querySelectorAll(".star")) b.addEventListener("click", () => rate(Number(b.dataset.score)));
document.addEventListener("keydown", (ev) => {
  if (ev.target.closest("input, textarea, select") || ev.ctrlKey || ev.metaKey || ev.altKey) return;
  if (["1", "2", "3", "4", "5"].includes(ev.key)) rate(Number(ev.key));
});
