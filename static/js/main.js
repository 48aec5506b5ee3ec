// threadrecon debugger page: starts a session, embeds its viser view, long-polls its state and
// hands each new state to the panels (one module each). Everything goes through the REST API.
import { $, S, api, showError } from "./core.js";
import { loadFrames, renderFrames } from "./frames.js";
import "./stages.js";
import "./check.js";
import { buildOverlayToggles, knownOverlays, loadImages, shownOverlays } from "./images.js";
import "./rating.js";
import "./corrections.js";
import { loadPresetList } from "./presets.js";
import "./exports.js";
import { startEvaluationPanel } from "./evaluation.js";
import "./agreement.js";

S.frameHooks = (S.frameHooks || []).concat([loadImages]);

function applyState(st) {
  const frameChanged = S.frameId !== st.frame_id;
  S.state = st;
  S.frameId = st.frame_id;
  if (frameChanged) renderFrames();
  for (const fn of S.hooks) {
    try { fn(st); } catch (e) { console.error(e); }
  }
}

async function poll() {
  for (;;) {
    try {
      // a finished run's state brings the 2D overlays the page shows and does not hold
      const st = await api("GET", `/api/sessions/${S.session}?since=${S.version}&timeout=10&overlay=${knownOverlays()}&keys=${shownOverlays()}`);
      $("#conn").textContent = "connected"; $("#conn").className = "badge ok";
      if (st.version !== S.version || !S.state) {
        S.stateAt = { version: st.version, at: Date.now() };  // for scripts/bench_latency.py
        S.states = (S.states || 0) + 1;  // states taken (scripts/bench_latency.py --moves)
        S.version = st.version;
        applyState(st);
      }
    } catch (e) {
      $("#conn").textContent = e.status === 404 ? "session expired: reload the page" : "server unreachable";
      $("#conn").className = "badge bad";
      await new Promise((r) => setTimeout(r, 1000));
    }
  }
}

async function start() {
  S.info = await api("GET", "/api/info");
  $("#data-dir").textContent = S.info.data_dir;
  buildOverlayToggles();
  const sess = await api("POST", "/api/sessions");
  S.session = sess.session;
  await loadFrames();
  const host = location.hostname;
  const ws = `ws://${host}:${sess.viser_port}${sess.viser_path}`;
  $("#viewer").src = `http://${host}:${sess.viser_port}/?websocket=${encodeURIComponent(ws)}&hideViserLogo`;
  window.addEventListener("pagehide", () => {
    fetch(`/api/sessions/${S.session}`, { method: "DELETE", keepalive: true }).catch(() => {});
  });
  poll();
  await loadPresetList();
  await startEvaluationPanel();
}

start().catch((e) => showError(`Cannot start: ${e.message}`));
