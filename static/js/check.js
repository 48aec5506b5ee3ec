// Check panel: the check stage's verdict on the shown curve (ok / suspect / failed), every
// reason in words, the automatic 1-5 score (continuous, and its integer class) and the grasp point (state.check, app/views/check.py).
import { $, fill, fmt, h, onState } from "./core.js";

function renderCheck(st) {
  const c = st.check;
  const badge = $("#check-status");
  badge.textContent = c ? c.status : (st.status === "failed" ? "failed" : "not checked yet");
  badge.className = `badge st-${c ? c.status : st.status}`;
  badge.dataset.status = c ? c.status : "";
  $("#check-score").textContent = c ? `automatic score ${fmt(c.rating, 2)}/5 (class ${c.score})` : "";
  const reasons = c ? c.reasons : (st.status === "failed" && st.error ? [st.error] : []);
  fill("#check-reasons", reasons.map((r) => h("li", {}, r)));
  $("#check-reasons").hidden = reasons.length === 0;
  const g = c && c.grasp;
  $("#check-grasp").textContent = c
    ? (g ? `grasp point: confidence ${fmt(g.confidence, 2)}, ${fmt(g.distance, 1)} ${st.unit || ""} from the ${g.from_end} (free end); ` : "no grasp point; ") +
      `confidence along the curve: min ${fmt(c.confidence_min, 2)}, mean ${fmt(c.confidence_mean, 2)}`
    : "";
}

onState(renderCheck);
