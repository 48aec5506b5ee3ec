// A small SVG plotting module for the tuning panel: scatter plots (numeric or categorical x,
// colour by a third value, highlighted points) and horizontal bar charts. No library, no
// network: every label enters the SVG as text nodes.
const NS = "http://www.w3.org/2000/svg";
const MARGIN = { left: 54, right: 12, top: 22, bottom: 40 };  // plot margins (px) for axis labels

function el(tag, attrs = {}, text) {
  const e = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) if (v !== null && v !== undefined) e.setAttribute(k, String(v));
  if (text !== undefined) e.textContent = String(text);
  return e;
}

const finite = (v) => typeof v === "number" && Number.isFinite(v);

// About five round tick values covering [lo, hi].
export function ticks(lo, hi, n = 5) {
  if (!(hi > lo)) return [lo];
  const raw = (hi - lo) / n, mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((k) => k * mag).find((s) => s >= raw);
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(+v.toPrecision(12));
  return out;
}

function extent(values) {
  const v = values.filter(finite);
  if (!v.length) return [0, 1];
  let lo = Math.min(...v), hi = Math.max(...v);
  const nonNegative = lo >= 0;  // a rate or a time: the axis does not go below 0
  if (lo === hi) { const pad = Math.abs(lo) * 0.1 || 0.5; lo -= pad; hi += pad; }
  const pad = (hi - lo) * 0.05;
  return [nonNegative ? Math.max(0, lo - pad) : lo - pad, hi + pad];
}

const label = (v) => (Math.abs(v) >= 1e4 || (Math.abs(v) < 1e-3 && v !== 0)) ? v.toExponential(1) : String(+v.toPrecision(4));

// Colour of t in [0, 1]: dark blue (low) to yellow (high).
export function ramp(t) {
  const c = Math.max(0, Math.min(1, finite(t) ? t : 0.5));
  const stops = [[48, 18, 110], [33, 145, 140], [253, 231, 37]];
  const [a, b, u] = c < 0.5 ? [stops[0], stops[1], c * 2] : [stops[1], stops[2], (c - 0.5) * 2];
  return `rgb(${a.map((x, i) => Math.round(x + (b[i] - x) * u)).join(",")})`;
}

// points: [{x, y, c?, hi?, title?, id?}]; x numeric, or an index into opt.xCats.
// opt: {width, height, xLabel, yLabel, title, xCats, cLabel, onClick(point)}.
export function scatter(points, opt = {}) {
  const W = opt.width || 300, H = opt.height || 210;
  const M = opt.cLabel ? { ...MARGIN, top: MARGIN.top + 12 } : MARGIN;  // a second title line
  const svg = el("svg", { viewBox: `0 0 ${W} ${H}`, width: W, height: H, class: "plot", role: "img" });
  if (opt.title) svg.append(el("text", { x: W / 2, y: 14, "text-anchor": "middle", class: "plot-title" }, opt.title));
  const pts = points.filter((p) => finite(p.x) && finite(p.y));
  const cats = opt.xCats;
  const [x0, x1] = cats ? [-0.5, cats.length - 0.5] : extent(pts.map((p) => p.x));
  const [y0, y1] = extent(pts.map((p) => p.y));
  const sx = (x) => M.left + ((x - x0) / (x1 - x0)) * (W - M.left - M.right);
  const sy = (y) => H - M.bottom - ((y - y0) / (y1 - y0)) * (H - M.top - M.bottom);
  const axes = el("g", { class: "axes" });
  axes.append(el("line", { x1: M.left, y1: H - M.bottom, x2: W - M.right, y2: H - M.bottom }));
  axes.append(el("line", { x1: M.left, y1: M.top, x2: M.left, y2: H - M.bottom }));
  const xt = cats ? cats.map((_, i) => i) : ticks(x0, x1);
  for (const t of xt) {
    axes.append(el("line", { x1: sx(t), x2: sx(t), y1: H - M.bottom, y2: H - M.bottom + 4 }));
    axes.append(el("text", { x: sx(t), y: H - M.bottom + 15, "text-anchor": "middle" }, cats ? String(cats[t]) : label(t)));
  }
  for (const t of ticks(y0, y1, 4)) {
    axes.append(el("line", { x1: M.left - 4, x2: M.left, y1: sy(t), y2: sy(t) }));
    axes.append(el("text", { x: M.left - 6, y: sy(t) + 3, "text-anchor": "end" }, label(t)));
  }
  if (opt.xLabel) axes.append(el("text", { x: (M.left + W - M.right) / 2, y: H - 6, "text-anchor": "middle", class: "axis-label" }, opt.xLabel));
  if (opt.yLabel) axes.append(el("text", { x: 12, y: (M.top + H - M.bottom) / 2, "text-anchor": "middle", class: "axis-label", transform: `rotate(-90 12 ${(M.top + H - M.bottom) / 2})` }, opt.yLabel));
  svg.append(axes);
  const cs = pts.map((p) => p.c).filter(finite);
  const [c0, c1] = cs.length ? [Math.min(...cs), Math.max(...cs)] : [0, 1];
  const dots = el("g", { class: "dots" });
  for (const p of [...pts].sort((a, b) => Number(!!a.hi) - Number(!!b.hi))) {  // highlighted on top
    const fill = finite(p.c) ? ramp(c1 > c0 ? (p.c - c0) / (c1 - c0) : 0.5) : "var(--accent, #3b82f6)";
    const dot = el("circle", { cx: sx(p.x), cy: sy(p.y), r: p.hi ? 5.5 : 3.5, fill, class: p.hi ? "hi" : "", "data-id": p.id });
    if (p.title) dot.append(el("title", {}, p.title));
    if (opt.onClick) dot.addEventListener("click", () => opt.onClick(p));
    dots.append(dot);
  }
  svg.append(dots);
  if (opt.cLabel && cs.length) svg.append(el("text", { x: W / 2, y: 27, "text-anchor": "middle", class: "axis-label" }, `colour: ${opt.cLabel} ${label(c0)}…${label(c1)}`));
  return svg;
}

// items: [{label, value}] drawn as horizontal bars (value >= 0), largest first.
export function bars(items, opt = {}) {
  const rows = items.filter((d) => finite(d.value)).sort((a, b) => b.value - a.value);
  const W = opt.width || 300, row = 20, H = MARGIN.top + rows.length * row + 10;
  const svg = el("svg", { viewBox: `0 0 ${W} ${H}`, width: W, height: H, class: "plot", role: "img" });
  if (opt.title) svg.append(el("text", { x: W / 2, y: 14, "text-anchor": "middle", class: "plot-title" }, opt.title));
  const M = MARGIN, left = 130, vmax = Math.max(...rows.map((d) => d.value), 1e-12);
  rows.forEach((d, i) => {
    const y = M.top + i * row;
    svg.append(el("text", { x: left - 6, y: y + 13, "text-anchor": "end" }, d.label));
    const w = (d.value / vmax) * (W - left - 50);
    const bar = el("rect", { x: left, y: y + 3, width: Math.max(w, 1), height: row - 6, class: "bar" });
    bar.append(el("title", {}, `${d.label}: ${label(d.value)}`));
    svg.append(bar);
    svg.append(el("text", { x: left + w + 4, y: y + 13 }, label(d.value)));
  });
  return svg;
}
