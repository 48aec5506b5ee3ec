// Stages panel: the stepper, its buttons, the error box and the metrics (labels from /api/info).
import { $, S, api, fill, fmt, h, metricLabel, onState, showError } from "./core.js";

function renderStepper(st) {
  fill("#stepper", st.stages.map((s, i) => {
    const ms = s.ms === undefined || s.ms === null ? "" : (s.status === "cached" ? "cached" : `${s.ms.toFixed(1)} ms`);
    return h("li", { dataset: { stage: s.stage, status: s.status }, class: `${s.status} ${s.revealed ? "" : "hidden"}` },
      h("span", {}, i + 1), h("span", {}, s.stage), h("span", { class: "ms" }, s.revealed ? ms : "hidden"));
  }));
}

function renderMetrics(st) {
  const m = st.metrics || {};
  const total = st.stages.reduce((a, s) => a + (s.ms || 0), 0);
  const rows = [["status", st.status], ["this run (ms, cached stages 0)", fmt(total, 1)]];
  for (const { key } of S.info.metrics) if (m[key] !== undefined && m[key] !== null) rows.push([metricLabel(key), fmt(m[key])]);
  fill("#metrics tbody", rows.map(([k, v]) => h("tr", {}, h("td", {}, k), h("td", {}, v))));
}

onState((st) => {
  $("#preset-badge").textContent = st.preset;
  renderStepper(st);
  renderMetrics(st);
  showError(st.error ? `${st.status === "failed" ? "Failed" : "Note"}: ${st.error}` : "");
});

for (const action of ["run", "next", "all"]) {
  $(`#btn-${action}`).addEventListener("click", () =>
    api("POST", `/api/sessions/${S.session}/step`, { action }).catch((e) => showError(e.message)));
}
