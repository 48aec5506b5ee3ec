// Shared state and helpers of the debugger page. Server and user strings enter the DOM only
// through textContent (h() below builds elements that way); nothing is written as HTML.

export const S = {
  session: null, info: null, frames: [], frameId: null, version: -1, state: null,
  overlay: null, overlayVersion: -1, images: {}, imageFrame: null, pixel: null,
  hooks: [],  // functions(state) called after each new state (one per panel)
};
window.threadrecon = S;  // for the browser tests and the console

export const $ = (sel) => document.querySelector(sel);
export const enc = (id) => id.split("/").map(encodeURIComponent).join("/");
export const fmt = (v, d = 3) => (v === null || v === undefined || Number.isNaN(v)) ? "–" : Number(v).toFixed(d);

// h("td", {class: "x", dataset: {frame: id}}, "text", child): an element; strings become text.
export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "dataset") Object.assign(el.dataset, v);
    else if (k === "class") el.className = v;
    else if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else el.setAttribute(k, String(v));
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

// Replace the children of `parent` (a selector or an element) by `children`.
export function fill(parent, ...children) {
  const el = typeof parent === "string" ? $(parent) : parent;
  el.replaceChildren(...children.flat());
}

export function cell(v) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(3);
  return String(v);
}

export function metricLabel(key) {
  const m = S.info && S.info.metrics.find((x) => x.key === key);
  return m ? (m.unit ? `${m.label} (${m.unit})` : m.label) : key;
}

export async function api(method, url, body) {
  const opt = { method, headers: {} };
  if (body !== undefined) { opt.headers["Content-Type"] = "application/json"; opt.body = JSON.stringify(body); }
  const r = await fetch(url, opt);
  const text = await r.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = { detail: text }; }
  if (!r.ok) {
    const detail = data && data.detail;
    const msg = typeof detail === "string" ? detail : JSON.stringify(detail);
    const err = new Error(msg || `${r.status}`);
    err.status = r.status;
    throw err;
  }
  return data;
}

export function showError(msg) {
  const box = $("#error");
  box.hidden = !msg;
  box.textContent = msg || "";
}

export function onState(fn) { S.hooks.push(fn); }
