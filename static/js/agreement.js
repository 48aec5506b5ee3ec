// Agreement panel: the check's automatic 1-5 score against the person's ratings of the rated
// frames (/api/ratings/agreement): a 5x5 confusion table and the Spearman rank correlation.
import { $, S, api, fill, fmt, h } from "./core.js";

function renderAgreement(got) {
  const scores = got.scores;
  fill("#agreement-table thead", h("tr", {}, h("th", {}, "rating ↓ automatic →"), scores.map((s) => h("th", {}, s))));
  fill("#agreement-table tbody", got.confusion.map((row, i) => h("tr", { dataset: { rating: scores[i] } },
    h("th", {}, scores[i]),
    row.map((n, j) => h("td", { class: n ? (i === j ? "agree" : "disagree") : "", dataset: { auto: scores[j] } }, n)))));
  const ev = got.evaluation;
  const source = ev ? `scores of saved evaluation #${ev.id}${ev.same_params ? "" : ` (other settings, preset ${ev.preset})`}`
    : "no saved evaluation: evaluate the dataset to score the frames";
  const rho = got.spearman === null ? `Spearman: – (${got.spearman_note})` : `Spearman ${fmt(got.spearman, 2)}`;
  const parts = [`${got.n} of ${got.rated} rated frames scored`, rho];
  if (got.n) parts.push(`exact ${fmt(100 * got.exact, 0)} %, within one ${fmt(100 * got.within_one, 0)} %`);
  if (got.missing.length) parts.push(`no score for ${got.missing.length}`);
  $("#agreement-brief").textContent = `${parts.join("; ")}; ${source}`;
}

async function showAgreement() {
  renderAgreement(await api("GET", `/api/ratings/agreement?session=${encodeURIComponent(S.session)}`));
}

$("#agreement-refresh").addEventListener("click", () => showAgreement().catch((e) => { $("#agreement-brief").textContent = e.message; }));
