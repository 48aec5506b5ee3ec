// Presets panel: load a preset (built-in or the user's), save the current values as a user
// preset, the difference from the defaults, reset.
import { $, S, api, fill, h, onState } from "./core.js";

export async function loadPresetList(select) {
  const names = await api("GET", "/api/presets");
  const sel = $("#preset-select");
  fill(sel, names.map((n) => h("option", { value: n }, n)));
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

onState((st) => {
  fill("#preset-diff tbody", st.diff.length
    ? st.diff.map((d) => h("tr", {}, h("td", {}, d.key), h("td", {}, `${d.value} `, h("span", { class: "hint" }, `(${d.base})`))))
    : [h("tr", {}, h("td", { class: "hint" }, "none: the paper's defaults"), h("td"))]);
});

$("#preset-load").addEventListener("click", usePreset);
$("#preset-save").addEventListener("click", savePreset);
$("#params-reset").addEventListener("click", () => api("POST", `/api/sessions/${S.session}/params/reset`).catch((e) => presetMsg(e.message, true)));
