// Exports panel: the current frame's spline and point clouds (the list comes from /api/info).
import { S, fill, h, onState } from "./core.js";

onState((st) => {
  const ok = st.stages.some((s) => s.stage === "camera" && ["done", "cached", "fallback"].includes(s.status));
  fill("#exports", ok
    ? S.info.exports.map((n) => h("a", { href: `/api/sessions/${encodeURIComponent(S.session)}/export/${encodeURIComponent(n)}`, download: "" }, n))
    : [h("span", { class: "hint" }, "run every stage first")]);
});
