// The comparison of numbers of trust states a model was chosen by (issue 40): a table of every candidate and a
// small plot of the held-out log-likelihood per trial ± SE against the number of states, the chosen one marked.

import { el, heading, number, row, svg, table } from "./admin-ui.js";

const PLOT = { width: 360, height: 190, left: 62, right: 16, top: 14, bottom: 40 };
const TITLE = "Which number of trust states the data support";

/** The section's nodes for a model's `selection` (none when it has none). */
export function selectionSection(selection) {
  if (!selection) return [];
  const chosen = selection.chosen;
  const rows = selection.candidates.map((c) => row({ class: c.n_states === chosen ? "chosen" : null },
    String(c.n_states), [number(c.loglik, 2), true], [String(c.n_free), true], [number(c.bic, 1), true],
    [number(c.icl, 1), true], [`${number(c.held_out_per_trial, 4)} ± ${number(c.held_out_se, 4)}`, true],
    c.n_states === chosen ? "chosen" : ""));
  const headers = ["Trust states", ["Log-likelihood", true], ["Parameters", true], ["BIC", true], ["ICL", true],
    ["Held-out log-likelihood per trial ± SE", true], "Choice"];
  const grid = table("selection-heading", headers, rows);
  grid.classList.add("selection-table");
  return [heading("selection-heading", TITLE),
    el("div", { class: "table-scroll selection-scroll" }, grid),
    selectionPlot(selection),
    el("p", { class: "selection-reason" }, `Chosen: ${selection.reason}.`),
    el("p", { class: "muted small" }, `${selection.folds}-fold cross-validation by participant, seed `
      + `${selection.seed}. Held-out: the log-likelihood of each fold's participants under the fit on the others, `
      + "per trial (higher is better). BIC counts trials as its sample size; ICL adds the uncertainty of the state "
      + "paths. Lower BIC and ICL are better; they are shown beside the choice, not used for it.")];
}

/** The section's nodes for a model fitted with trust ratings (none otherwise): each state's mean rating, and
 * whether the ratings improved the model of reliance on held-out participants. */
export function ratingsSection(ratings) {
  if (!ratings) return [];
  const [lowest, highest] = ratings.scale;
  const rows = ratings.mean_rating.map((mean, j) => row({}, `state ${j}`, [number(mean, 1), true],
    [number(ratings.sd_rating[j], 1), true]));
  const nodes = [heading("ratings-heading", "What the trust ratings add"),
    el("div", { class: "table-scroll selection-scroll" }, table("ratings-heading", [
      "Trust state (lowest reliance first)", [`Mean rating (${lowest}–${highest})`, true],
      ["SD of a rating", true]], rows))];
  const c = ratings.comparison;
  if (c) {
    nodes.push(el("p", { class: "ratings-verdict" }, `With ratings, ${c.n_states} states: held-out reliance `
      + `${number(c.held_out_with_ratings, 4)} per trial; without: ${number(c.held_out_without_ratings, 4)}. `
      + `${c.verdict.charAt(0).toUpperCase()}${c.verdict.slice(1)}.`));
  }
  nodes.push(el("p", { class: "muted small" }, `${ratings.n_ratings} ratings, each placed at the last trial of its `
    + "shelf and modelled as a beta-binomial of the trust state. Both fits are scored on the held-out "
    + "participants' reliance alone, the quantity the robot's policy uses."));
  return nodes;
}

/** Held-out log-likelihood per trial ± SE against the number of states; the chosen number filled and labelled. */
export function selectionPlot(selection) {
  const { width, height, left, right, top, bottom } = PLOT;
  const points = selection.candidates.map((c) => ({ k: c.n_states, y: c.held_out_per_trial, se: c.held_out_se }));
  const lows = points.map((p) => p.y - p.se);
  const highs = points.map((p) => p.y + p.se);
  let [lo, hi] = [Math.min(...lows), Math.max(...highs)];
  const pad = (hi - lo) * 0.12 || Math.abs(hi) * 0.01 || 0.01;
  [lo, hi] = [lo - pad, hi + pad];
  const x = (i) => left + (points.length === 1 ? 0.5 : i / (points.length - 1)) * (width - left - right - 48) + 24;
  const y = (v) => top + (hi - v) / (hi - lo) * (height - top - bottom);
  const label = `Held-out log-likelihood per trial ± SE by number of trust states: `
    + points.map((p) => `${p.k} states ${number(p.y, 4)} ± ${number(p.se, 4)}`).join("; ")
    + `. Chosen: ${selection.chosen} states.`;
  const chart = svg("svg", { class: "selection-plot", width, height, viewBox: `0 0 ${width} ${height}`, role: "img",
    "aria-label": label });
  for (const v of [lo + pad, (lo + hi) / 2, hi - pad]) {
    chart.append(svg("line", { class: "grid-line", x1: left, x2: width - right, y1: y(v), y2: y(v) }),
      text(number(v, 3), { x: left - 6, y: y(v) + 4, "text-anchor": "end" }));
  }
  chart.append(svg("line", { class: "axis", x1: left, x2: left, y1: top, y2: height - bottom }),
    svg("line", { class: "axis", x1: left, x2: width - right, y1: height - bottom, y2: height - bottom }));
  points.forEach((p, i) => {
    const group = svg("g", { class: p.k === selection.chosen ? "chosen" : "" });
    group.append(svg("line", { class: "bar", x1: x(i), x2: x(i), y1: y(p.y - p.se), y2: y(p.y + p.se) }),
      svg("line", { class: "bar", x1: x(i) - 5, x2: x(i) + 5, y1: y(p.y - p.se), y2: y(p.y - p.se) }),
      svg("line", { class: "bar", x1: x(i) - 5, x2: x(i) + 5, y1: y(p.y + p.se), y2: y(p.y + p.se) }),
      svg("circle", { class: "dot", cx: x(i), cy: y(p.y), r: p.k === selection.chosen ? 5 : 4 }),
      text(String(p.k), { x: x(i), y: height - bottom + 15, "text-anchor": "middle" }));
    if (p.k === selection.chosen) group.append(text("chosen", { x: x(i) + 9, y: y(p.y) - 6 }));
    chart.append(group);
  });
  chart.append(text("trust states", { x: (left + width - right) / 2, y: height - 6, "text-anchor": "middle" }),
    text("held-out per trial", { x: 12, y: (top + height - bottom) / 2, "text-anchor": "middle",
      transform: `rotate(-90 12 ${(top + height - bottom) / 2})` }));
  return chart;
}

function text(content, attrs) {
  const node = svg("text", attrs);
  node.textContent = content;
  return node;
}
