// Tuning panel: choose parameters and ranges around the current sliders, start a tune on the
// data folder, follow it trial by trial, cancel it; then the best trials, parameter importance,
// objective vs each parameter and the Pareto front, and one click to load a trial into the
// sliders or save it as a user preset. Everything goes through /api/tune.
import { $, S, api, cell, fill, h } from "./core.js";
import { bars, scatter } from "./plot.js";

const T = { trials: [], job: null, results: null, selected: null, polling: false };
window.threadreconTune = T;  // for the browser tests and the console
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const numeric = (c) => c.kind === "slider" || c.kind === "number";

function controlOf(key) { return S.info.controls.find((c) => c.key === key); }

function currentValue(c) {
  const p = S.state && S.state.params;
  return p && p[c.stage] ? p[c.stage][c.name] : undefined;
}

function msg(text, bad) {
  const m = $("#tune-msg");
  m.textContent = text || "";
  m.style.color = bad ? "var(--bad)" : "";
}

// --- the space ---------------------------------------------------------------------------

function addParam(key) {
  const c = controlOf(key);
  if (!c || document.querySelector(`#tune-space tr[data-key="${CSS.escape(key)}"]`)) return;
  const cur = currentValue(c);
  let inputs;
  if (numeric(c)) {
    const step = c.step || (c.integer ? 1 : "any");
    const box = (cls, v, title) => h("input", { type: "number", class: cls, value: v, step, min: c.min, max: c.max, title });
    inputs = [box("low", c.min, "lowest value"), box("high", c.max, "highest value"),
      h("input", { type: "number", class: "step", step: "any", min: 0, placeholder: c.integer ? "1" : "continuous", title: "step (empty: continuous; a grid needs one)" })];
  } else {
    const opts = c.kind === "checkbox" ? ["true", "false"] : c.options;
    inputs = [h("input", { type: "text", class: "choices", value: opts.join(", "), title: "choices, comma separated" })];
  }
  const row = h("tr", { dataset: { key } }, h("td", { title: `${c.label || c.name}${c.unit ? ` (${c.unit})` : ""}` }, key),
    h("td", {}, cell(cur)), numeric(c) ? inputs.map((i) => h("td", {}, i)) : h("td", { colspan: 3, class: "choices-cell" }, inputs[0]),
    h("td", {}, h("button", { class: "remove", title: "do not vary", onclick: () => row.remove() }, "×")));
  $("#tune-space tbody").append(row);
}

function choiceValue(c, text) {
  if (c.kind === "checkbox") return text === "true";
  return text;
}

// {stage: {name: [choices] | {low, high[, step]}}} from the rows; throws a message.
function readSpace() {
  const space = {};
  for (const row of document.querySelectorAll("#tune-space tbody tr")) {
    const c = controlOf(row.dataset.key);
    let entry;
    if (numeric(c)) {
      const get = (cls) => row.querySelector(`.${cls}`).value.trim();
      const low = Number(get("low")), high = Number(get("high"));
      if (get("low") === "" || get("high") === "" || !Number.isFinite(low) || !Number.isFinite(high)) throw new Error(`${c.key}: give a low and a high value`);
      entry = { low, high };
      if (get("step") !== "") entry.step = Number(get("step"));
    } else {
      entry = row.querySelector(".choices").value.split(",").map((s) => s.trim()).filter(Boolean).map((s) => choiceValue(c, s));
    }
    (space[c.stage] = space[c.stage] || {})[c.name] = entry;
  }
  if (!Object.keys(space).length) throw new Error("add at least one parameter to vary");
  return space;
}

// --- a run -------------------------------------------------------------------------------

async function startTune() {
  let space;
  try { space = readSpace(); } catch (e) { msg(e.message, true); return; }
  const trials = $("#tune-trials-n").value.trim(), frames = $("#tune-frames").value.trim();
  const constraint = $("#tune-constraint").value.trim();
  const body = {
    session: S.session, space, objective: $("#tune-objective").value, mode: $("#tune-mode").value,
    trials: trials === "" ? null : Number(trials), max_frames: frames === "" ? null : Number(frames),
    constraints: constraint ? constraint.split(",").map((s) => s.trim()).filter(Boolean) : [],
  };
  try { await api("POST", "/api/tune", body); } catch (e) { msg(e.message, true); return; }
  msg("");
  T.trials = []; T.results = null; T.selected = null;
  fill("#tune-results", []);
  follow();
}

async function follow() {
  if (T.polling) return;
  T.polling = true;
  $("#tune-start").disabled = true; $("#tune-cancel").disabled = false;
  try {
    for (;;) {
      let snap;
      try { snap = await api("GET", `/api/tune/current?since=${T.trials.length}`); } catch (e) { msg(e.message, true); break; }
      if (!snap) break;
      T.job = snap;
      T.trials = T.trials.concat(snap.trials);
      renderProgress(snap);
      if (snap.state !== "running") {
        if (snap.error) msg(`tune failed: ${snap.error}`, true);
        await loadResults();
        break;
      }
      await sleep(300);
    }
  } finally {
    T.polling = false;
    $("#tune-start").disabled = false; $("#tune-cancel").disabled = true;
  }
}

function renderProgress(snap) {
  const f = snap.frames;
  const part = f.total ? f.done / f.total : 0;
  $("#tune-progress").max = snap.target;
  $("#tune-progress").value = Math.min(snap.target, snap.done + (snap.state === "running" ? part : 0));
  const st = $("#tune-status");
  st.dataset.state = snap.state;
  st.textContent = `${snap.state}: ${snap.done}/${snap.target} trials` +
    (snap.state === "running" && f.total ? `, trial ${snap.done}: frame ${f.done}/${f.total}` : "") +
    `, ${snap.elapsed_s.toFixed(1)} s (store ${snap.store})`;
  const obj = snap.objective;
  fill("#tune-live thead", h("tr", {}, ["trial", "state", obj, "failures", "time (ms)"].map((c) => h("th", {}, c)), snap.keys.map((k) => h("th", {}, k))));
  fill("#tune-live tbody", T.trials.slice().reverse().map((t) => h("tr", { dataset: { trial: t.number } },
    h("td", {}, t.number), h("td", { class: `st-${t.state.toLowerCase()}` }, t.feasible || t.state !== "COMPLETE" ? t.state.toLowerCase() : "infeasible"),
    h("td", {}, cell(t.objectives[obj])), h("td", {}, pct(t.objectives.failure_rate)), h("td", {}, cell(t.objectives.time)),
    snap.keys.map((k) => h("td", {}, cell(t.values[k]))))));
}

const pct = (v) => (typeof v === "number" ? `${(100 * v).toFixed(0)} %` : "–");

// --- results -----------------------------------------------------------------------------

async function loadResults() {
  try { T.results = await api("GET", "/api/tune/current/results"); } catch (e) { msg(e.message, true); return; }
  renderResults(T.results);
}

function trialButtons(n) {
  return [h("button", { class: "load", dataset: { trial: n }, title: "put this setting into the sliders", onclick: () => loadTrial(n) }, "Load"),
    h("button", { class: "save", dataset: { trial: n }, title: "save as a user preset (name above)", onclick: () => saveTrial(n) }, "Save")];
}

function renderResults(res) {
  const byN = new Map(res.trials.map((t) => [t.number, t]));
  const obj = res.objective.name, keys = res.dimensions.map((d) => d.key);
  const best = res.best.map((n) => byN.get(n));
  const table = h("table", { id: "tune-best", class: "grid" },
    h("thead", {}, h("tr", {}, ["#", "trial", `${obj} (${res.objective.direction})`, "failures", "time (ms)", "feasible", ...keys, ""].map((c) => h("th", {}, c)))),
    h("tbody", {}, best.map((t, i) => h("tr", { dataset: { trial: t.number } }, h("td", {}, i + 1), h("td", {}, t.number),
      h("td", {}, cell(t.objectives[obj])), h("td", {}, pct(t.objectives.failure_rate)), h("td", {}, cell(t.objectives.time)),
      h("td", {}, t.feasible ? "yes" : "no"), keys.map((k) => h("td", {}, cell(t.values[k]))), h("td", {}, trialButtons(t.number))))));
  const done = res.trials.filter((t) => t.state === "COMPLETE");
  const bestN = new Set(res.best.slice(0, 1));
  const click = (p) => selectTrial(p.id);
  const tip = (t) => `trial ${t.number}: ${obj} ${cell(t.objectives[obj])}; ` + keys.map((k) => `${k}=${cell(t.values[k])}`).join(", ");
  const perParam = res.dimensions.map((d) => {
    const cats = d.choices.length ? d.choices.map(String) : null;
    const pts = done.map((t) => ({ x: cats ? cats.indexOf(String(t.values[d.key])) : t.values[d.key], y: t.objectives[obj], id: t.number, hi: bestN.has(t.number), title: tip(t) }));
    return scatter(pts, { title: `${obj} vs ${d.key}`, xLabel: d.key, yLabel: obj, xCats: cats, onClick: click });
  });
  const [acc, fr, tm] = res.pareto.axes, front = new Set(res.pareto.front);
  const pp = (x, y, c) => done.map((t) => ({ x: t.objectives[x], y: t.objectives[y], c: t.objectives[c], id: t.number, hi: front.has(t.number), title: `${tip(t)}${front.has(t.number) ? " (Pareto front)" : ""}` }));
  const imp = Object.entries(res.importance).map(([label, value]) => ({ label, value }));
  fill("#tune-results",
    h("h3", {}, "Best trials"), h("div", { class: "scroll" }, table),
    h("div", { class: "tune-row" }, h("input", { id: "tune-preset-name", type: "text", maxlength: 64, placeholder: "preset name for Save" }),
      h("span", { id: "tune-selected", class: "hint" }, "click a point of a plot to pick its trial")),
    h("div", { class: "plots" },
      h("figure", { id: "tune-importance" }, imp.length ? bars(imp, { title: `parameter importance for ${obj} (PED-ANOVA)` }) : h("p", { class: "hint" }, res.importance_note)),
      h("figure", { id: "tune-pareto" },
        scatter(pp(acc, fr, tm), { title: `Pareto front: ${acc} vs ${fr}`, xLabel: acc, yLabel: fr, cLabel: "time (ms)", onClick: click }),
        scatter(pp(acc, tm, fr), { title: `Pareto front: ${acc} vs ${tm}`, xLabel: acc, yLabel: `${tm} (ms)`, cLabel: "failures", onClick: click })),
      h("figure", { id: "tune-scatter" }, perParam)),
    h("p", { class: "hint" }, `big dots: the best trial (plots of ${obj}) or the Pareto front of ${acc}, failure rate and time (the other plots); constraints: ${res.constraints.join(", ") || "none"}`));
}

function selectTrial(n) {
  const t = T.results && T.results.trials.find((x) => x.number === n);
  if (!t) return;
  T.selected = n;
  fill("#tune-selected", `trial ${n}: ` + Object.entries(t.values).map(([k, v]) => `${k}=${cell(v)}`).join(", ") + " ", trialButtons(n));
}

async function loadTrial(n) {
  try {
    await api("POST", `/api/tune/current/trials/${n}/load`, { session: S.session });
    msg(`trial ${n} loaded into the sliders`);
  } catch (e) { msg(e.message, true); }
}

async function saveTrial(n) {
  const box = $("#tune-preset-name"), name = box ? box.value.trim() : "";
  if (!name) { msg("type a preset name first", true); return; }
  try {
    await api("POST", `/api/tune/current/trials/${n}/preset`, { name });
    msg(`trial ${n} saved as preset ${name}`);
    const sel = $("#preset-select");
    if (sel && ![...sel.options].some((o) => o.value === name)) sel.append(h("option", { value: name }, name));
  } catch (e) { msg(e.status === 409 ? `${e.message} (presets are never overwritten from here: pick another name)` : e.message, true); }
}

// --- start-up ----------------------------------------------------------------------------

async function init() {
  while (!S.info || !S.session) await sleep(100);
  const objectives = await api("GET", "/api/tune/objectives");
  fill("#tune-objective", objectives.map((o) => h("option", { value: o.name, title: o.doc }, `${o.name} (${o.direction})`)));
  fill("#tune-param", S.info.controls.map((c) => h("option", { value: c.key }, `${c.key} (${c.label})`)));
  $("#tune-add").addEventListener("click", () => addParam($("#tune-param").value));
  $("#tune-start").addEventListener("click", startTune);
  $("#tune-cancel").addEventListener("click", () => api("POST", "/api/tune/current/cancel").catch((e) => msg(e.message, true)));
  const cur = await api("GET", "/api/tune/current");
  if (cur) follow();  // a running tune is followed; a finished one shows its results
}

init().catch((e) => msg(`tuning panel: ${e.message}`, true));
