// Evaluation panel: whole-dataset evaluation, comparison of two saved ones, and the Table II
// of rated frames (its figures are the stored ones of a saved evaluation).
import { $, S, api, cell, fill, h, metricLabel } from "./core.js";

const EVAL_COLUMNS = ["status", "auto_rating", "auto_score", "e_S_mm", "e_S_max_mm", "e_length_mm", "left_mean_px", "right_mean_px",
  "coverage_left", "coverage_right", "n_keypoints", "ms_total", "error"];
const STATUSES = ["ok", "suspect", "failed"];
const COMPARE_COLUMNS = ["e_S_mm", "e_S_max_mm", "e_length_mm", "left_mean_px", "right_mean_px", "coverage_left", "coverage_right"];
const RATING_COLUMNS = ["score", "left_mean_px", "left_max_px", "right_mean_px", "right_max_px", "coverage_left", "coverage_right", "same_params", "note"];

const head = (cols) => h("tr", {}, h("th", {}, "frame"), cols.map((c) => h("th", {}, metricLabel(c))));

function renderEvaluation(ev, label) {
  fill("#eval-table thead", head(EVAL_COLUMNS));
  fill("#eval-table tbody", (ev.rows || []).map((r) => h("tr", { dataset: { frame: r.frame } },
    h("td", {}, r.frame), EVAL_COLUMNS.map((k) => h("td", { class: k === "status" ? `st-${r.status}` : `col-${k}` }, cell(r[k]))))));
  // counts per status of the rows so far (the summary lines come when the run is done)
  const rows = ev.rows || [];
  fill("#eval-counts", STATUSES.map((s) => h("span", { class: `st-${s}`, dataset: { status: s } },
    `${s} ${rows.filter((r) => r.status === s).length}`)));
  $("#eval-summary").textContent = (ev.summary || []).join("\n");
  $("#eval-brief").textContent = label;
}

let evalRows = [];
async function startEvaluation() {
  try {
    await api("POST", "/api/evaluations", { session: S.session });
  } catch (e) { $("#eval-status").textContent = e.message; }
  evalRows = [];
  $("#evaluation-section").open = true;
  pollEvaluation();
}

async function pollEvaluation() {
  $("#eval-cancel").disabled = false;
  $("#eval-start").disabled = true;
  for (;;) {
    let snap;
    try { snap = await api("GET", `/api/evaluations/current?since=${evalRows.length}`); } catch (e) { break; }
    if (!snap) break;
    evalRows = evalRows.concat(snap.rows);
    $("#eval-progress").max = snap.total; $("#eval-progress").value = snap.done;
    $("#eval-status").textContent = `${snap.state}: ${snap.done}/${snap.total}${snap.current ? ` (${snap.current})` : ""}, ${snap.elapsed_s.toFixed(1)} s, preset ${snap.preset}`;
    $("#eval-status").dataset.state = snap.state;
    renderEvaluation({ rows: evalRows, summary: snap.summary }, `${snap.state}, preset ${snap.preset}`);
    if (!["pending", "running"].includes(snap.state)) break;
    await new Promise((r) => setTimeout(r, 250));
  }
  $("#eval-cancel").disabled = true;
  $("#eval-start").disabled = false;
  loadEvaluationList();
}

async function loadEvaluationList() {
  const list = await api("GET", "/api/evaluations");
  for (const id of ["#cmp-a", "#cmp-b"]) {
    const sel = $(id), keep = sel.value;
    fill(sel, list.map((e) => h("option", { value: e.id }, `#${e.id} ${e.preset} (${e.params_hash}) ${e.created_at.slice(0, 16)}`)));
    if (keep) sel.value = keep;
  }
  if (list.length > 1 && !$("#cmp-a").dataset.touched) { $("#cmp-a").value = list[1].id; $("#cmp-b").value = list[0].id; }
}

async function compareEvaluations() {
  const a = $("#cmp-a").value, b = $("#cmp-b").value;
  if (!a || !b) return;
  const cmp = await api("GET", `/api/evaluations/compare?a=${encodeURIComponent(a)}&b=${encodeURIComponent(b)}`);
  fill("#cmp-table thead", h("tr", {}, h("th", {}, "frame"), h("th", {}, "status A"), h("th", {}, "B"),
    COMPARE_COLUMNS.map((c) => [h("th", {}, `${metricLabel(c)} A`), h("th", {}, "B"), h("th", {}, "B−A")])));
  const higherIsBetter = (c) => c.startsWith("coverage");
  fill("#cmp-table tbody", cmp.rows.map((r) => h("tr", {}, h("td", {}, r.frame),
    h("td", { class: `st-${r.status_a}` }, r.status_a), h("td", { class: `st-${r.status_b}` }, r.status_b), COMPARE_COLUMNS.map((c) => {
    const d = r[`${c}_diff`];
    const cls = d === null || Math.abs(d) < 1e-9 ? "" : ((d < 0) !== higherIsBetter(c) ? "better" : "worse");
    return [h("td", {}, cell(r[`${c}_a`])), h("td", {}, cell(r[`${c}_b`])), h("td", { class: cls }, cell(d))];
  }))));
}

async function showRatings() {
  const got = await api("GET", `/api/ratings/summary?session=${encodeURIComponent(S.session)}`);
  fill("#ratings-table thead", head(RATING_COLUMNS));
  fill("#ratings-table tbody", got.rows.map((r) => h("tr", { dataset: { frame: r.frame } },
    h("td", {}, r.frame), RATING_COLUMNS.map((k) => h("td", { class: `col-${k}` }, cell(r[k]))))));
  const s = got.summary, ev = got.evaluation;
  const source = ev ? `figures of saved evaluation #${ev.id} (${ev.same_params ? "current settings" : `other settings, preset ${ev.preset}`})`
    : "no saved evaluation: evaluate the dataset to fill the figures";
  $("#ratings-brief").textContent = s.rated
    ? `${s.rated} rated, mean score ${s.mean_score.toFixed(2)}, failure rate ${(100 * s.failure_rate).toFixed(0)} % (score < 3); ${source}`
    : "no rated frame yet";
}

export async function startEvaluationPanel() {
  $("#eval-start").addEventListener("click", startEvaluation);
  $("#eval-cancel").addEventListener("click", () => api("POST", "/api/evaluations/current/cancel").catch(() => {}));
  $("#cmp-go").addEventListener("click", () => compareEvaluations().catch((e) => fill("#cmp-table tbody", h("tr", {}, h("td", {}, e.message)))));
  for (const id of ["#cmp-a", "#cmp-b"]) $(id).addEventListener("change", () => { $("#cmp-a").dataset.touched = "1"; });
  $("#ratings-refresh").addEventListener("click", () => showRatings().catch((e) => { $("#ratings-brief").textContent = e.message; }));
  await loadEvaluationList();
  // reopening the page shows the last evaluation (a running one is followed)
  const cur = await api("GET", "/api/evaluations/current");
  if (cur && ["pending", "running"].includes(cur.state)) { pollEvaluation(); return; }
  const last = await api("GET", "/api/evaluations/last");
  if (last) renderEvaluation(last, `last saved: #${last.id}, preset ${last.preset}, ${last.created_at.slice(0, 16)}`);
  else $("#eval-brief").textContent = "(no saved evaluation yet)";
}
