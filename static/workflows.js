// Workflows of the debugger page: rating frames, presets, exports, whole-dataset evaluation,
// comparison of two evaluations, and the Table II of rated frames. Uses app.js's helpers.
"use strict";

// --- rating ----------------------------------------------------------------------------------

let ratingFor = null;

async function loadRating(frameId) {
  ratingFor = frameId;
  try {
    const r = await api("GET", `/api/frames/${enc(frameId)}/rating`);
    if (ratingFor === frameId) showRating(r);
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
  if (latest && document.activeElement !== $("#rating-note")) $("#rating-note").value = latest.note;
  const f = S.frames.find((x) => x.id === r.frame_id);
  if (f && f.rating !== (latest ? latest.score : null)) { f.rating = latest ? latest.score : null; renderFrames(); }
}

async function rate(score) {
  const frameId = S.frameId;
  if (!frameId) return;
  try {
    const r = await api("PUT", `/api/frames/${enc(frameId)}/rating`, {
      score, note: $("#rating-note").value, session: S.session,
    });
    if (S.frameId === frameId) showRating(r);
  } catch (e) { $("#rating-latest").textContent = `not saved: ${e.message}`; }
}

// --- presets ---------------------------------------------------------------------------------

async function loadPresetList(select) {
  const names = await api("GET", "/api/presets");
  const sel = $("#preset-select");
  sel.innerHTML = names.map((n) => `<option>${n}</option>`).join("");
  if (select && names.includes(select)) sel.value = select;
}

function presetMsg(text, bad) {
  const m = $("#preset-msg");
  m.textContent = text;
  m.style.color = bad ? "var(--bad)" : "";
}

async function usePreset() {
  const name = $("#preset-select").value;
  if (!name) return;
  try {
    await api("POST", `/api/sessions/${S.session}/preset`, { name });
    presetMsg(`loaded ${name}`);
  } catch (e) { presetMsg(e.message, true); }
}

async function savePreset() {
  const name = $("#preset-name").value.trim();
  if (!name) { presetMsg("type a name first", true); return; }
  const body = { name, session: S.session, overwrite: false };
  try {
    await api("POST", "/api/presets", body);
  } catch (e) {
    if (e.status !== 409) { presetMsg(e.message, true); return; }
    if (!window.confirm(`Preset "${name}" exists. Overwrite it?`)) { presetMsg("not saved: the preset exists", true); return; }
    try { await api("POST", "/api/presets", Object.assign(body, { overwrite: true })); } catch (e2) { presetMsg(e2.message, true); return; }
  }
  presetMsg(`saved ${name}`);
  $("#preset-name").value = "";
  loadPresetList(name);
}

function renderDiff(st) {
  const tbody = $("#preset-diff tbody");
  tbody.innerHTML = st.diff.length
    ? st.diff.map((d) => `<tr><td>${d.key}</td><td>${d.value} <span class="hint">(${d.base})</span></td></tr>`).join("")
    : `<tr><td class="hint">none: the paper's defaults</td><td></td></tr>`;
}

// --- exports ---------------------------------------------------------------------------------

const EXPORT_NAMES = ["spline.json", "spline.csv", "spline.ply", "stereo.ply", "reliable.ply", "keypoints.ply"];

function renderExports(st) {
  const ok = st.stages.some((s) => s.stage === "camera" && (s.status === "done" || s.status === "cached" || s.status === "fallback"));
  $("#exports").innerHTML = ok
    ? EXPORT_NAMES.map((n) => `<a href="/api/sessions/${S.session}/export/${n}" download>${n}</a>`).join("")
    : `<span class="hint">run every stage first</span>`;
}

// --- evaluation ------------------------------------------------------------------------------

const EVAL_COLUMNS = [
  ["status", "status"], ["e_S_mm", "e_S mm"], ["e_S_max_mm", "max mm"], ["e_length_mm", "len err mm"],
  ["left_mean_px", "L px"], ["right_mean_px", "R px"], ["coverage_left", "cov L"], ["coverage_right", "cov R"],
  ["n_keypoints", "keypoints"], ["ms_total", "ms"],
];

function cell(v) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(3);
  return String(v);
}

function renderEvalRows(rows) {
  $("#eval-table thead").innerHTML = `<tr><th>frame</th>${EVAL_COLUMNS.map(([, l]) => `<th>${l}</th>`).join("")}</tr>`;
  $("#eval-table tbody").innerHTML = rows.map((r) =>
    `<tr data-frame="${r.frame}"><td>${r.frame}</td>${EVAL_COLUMNS.map(([k]) => `<td class="${k === "status" ? `st-${r.status}` : ""}">${cell(r[k])}</td>`).join("")}</tr>`,
  ).join("");
}

function renderEvaluation(ev, label) {
  renderEvalRows(ev.rows || []);
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
  const opts = list.map((e) => `<option value="${e.id}">#${e.id} ${e.preset} (${e.params_hash}) ${e.created_at.slice(0, 16)}</option>`).join("");
  for (const id of ["#cmp-a", "#cmp-b"]) {
    const sel = $(id), keep = sel.value;
    sel.innerHTML = opts;
    if (keep) sel.value = keep;
  }
  if (list.length > 1 && !$("#cmp-a").dataset.touched) { $("#cmp-a").value = list[1].id; $("#cmp-b").value = list[0].id; }
}

async function compareEvaluations() {
  const a = $("#cmp-a").value, b = $("#cmp-b").value;
  if (!a || !b) return;
  const cmp = await api("GET", `/api/evaluations/compare?a=${a}&b=${b}`);
  const cols = ["e_S_mm", "e_S_max_mm", "e_length_mm", "left_mean_px", "right_mean_px", "coverage_left", "coverage_right"];
  $("#cmp-table thead").innerHTML = `<tr><th>frame</th>${cols.map((c) => `<th>${c} A</th><th>B</th><th>B−A</th>`).join("")}</tr>`;
  const higherIsBetter = (c) => c.startsWith("coverage");
  $("#cmp-table tbody").innerHTML = cmp.rows.map((r) => `<tr><td>${r.frame}</td>${cols.map((c) => {
    const d = r[`${c}_diff`];
    const cls = d === null || Math.abs(d) < 1e-9 ? "" : ((d < 0) !== higherIsBetter(c) ? "better" : "worse");
    return `<td>${cell(r[`${c}_a`])}</td><td>${cell(r[`${c}_b`])}</td><td class="${cls}">${cell(d)}</td>`;
  }).join("")}</tr>`).join("");
}

async function showRatings() {
  const got = await api("GET", `/api/ratings/summary?session=${S.session}`);
  const cols = [["score", "score"], ["left_mean_px", "L mean"], ["left_max_px", "L max"], ["right_mean_px", "R mean"], ["right_max_px", "R max"], ["coverage_left", "cov L"], ["coverage_right", "cov R"], ["same_params", "same params"], ["note", "note"]];
  $("#ratings-table thead").innerHTML = `<tr><th>frame</th>${cols.map(([, l]) => `<th>${l}</th>`).join("")}</tr>`;
  $("#ratings-table tbody").innerHTML = got.rows.map((r) => `<tr><td>${r.frame}</td>${cols.map(([k]) => `<td>${cell(r[k])}</td>`).join("")}</tr>`).join("");
  const s = got.summary;
  $("#ratings-brief").textContent = s.rated
    ? `${s.rated} rated, mean score ${s.mean_score.toFixed(2)}, failure rate ${(100 * s.failure_rate).toFixed(0)} % (score < 3); errors with the current settings`
    : "no rated frame yet";
}

// --- wiring ----------------------------------------------------------------------------------

let lastFrame = null;
S.hooks.push((st) => {
  if (st.frame_id && st.frame_id !== lastFrame) { lastFrame = st.frame_id; loadRating(st.frame_id); }
  renderDiff(st);
  renderExports(st);
});

function bindWorkflows() {
  for (const b of document.querySelectorAll(".star")) b.addEventListener("click", () => rate(Number(b.dataset.score)));
  document.addEventListener("keydown", (ev) => {
    if (ev.target.closest("input, textarea, select") || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    if (["1", "2", "3", "4", "5"].includes(ev.key)) rate(Number(ev.key));
  });
  $("#preset-load").addEventListener("click", usePreset);
  $("#preset-save").addEventListener("click", savePreset);
  $("#params-reset").addEventListener("click", () => api("POST", `/api/sessions/${S.session}/params/reset`).catch((e) => presetMsg(e.message, true)));
  $("#eval-start").addEventListener("click", startEvaluation);
  $("#eval-cancel").addEventListener("click", () => api("POST", "/api/evaluations/current/cancel").catch(() => {}));
  $("#cmp-go").addEventListener("click", () => compareEvaluations().catch((e) => { $("#cmp-table tbody").innerHTML = `<tr><td>${e.message}</td></tr>`; }));
  for (const id of ["#cmp-a", "#cmp-b"]) $(id).addEventListener("change", () => { $("#cmp-a").dataset.touched = "1"; });
  $("#ratings-refresh").addEventListener("click", () => showRatings().catch((e) => { $("#ratings-brief").textContent = e.message; }));
}

async function startWorkflows() {
  bindWorkflows();
  await loadPresetList();
  await loadEvaluationList();
  // reopening the page shows the last evaluation (a running one is followed)
  const cur = await api("GET", "/api/evaluations/current");
  if (cur && ["pending", "running"].includes(cur.state)) { pollEvaluation(); return; }
  const last = await api("GET", "/api/evaluations/last");
  if (last) renderEvaluation(last, `last saved: #${last.id}, preset ${last.preset}, ${last.created_at.slice(0, 16)}`);
  else $("#eval-brief").textContent = "(no saved evaluation yet)";
}

startWorkflows();
