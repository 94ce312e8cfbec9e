// Small DOM helpers of the dashboard. Nothing from the server is inserted as HTML: text only.

import { describe } from "./admin-api.js";

export const $ = (id) => document.getElementById(id);

const SVG_NS = "http://www.w3.org/2000/svg";

/** An element with attributes and children (strings become text nodes). */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) {
    if (value !== null && value !== undefined && value !== false) node.setAttribute(name, value === true ? "" : value);
  }
  node.append(...children.filter((c) => c !== null && c !== undefined));
  return node;
}

/** A cell given as text (or nodes), or as [content, numeric]: numbers are right-aligned. */
function cell(tag, spec, attrs = {}) {
  const [content, numeric] = Array.isArray(spec) && typeof spec[1] === "boolean" ? spec : [spec, false];
  return el(tag, { ...attrs, class: numeric ? "num" : null }, ...(Array.isArray(content) ? content : [content]));
}

/** A table row: the first cell is the row's header. */
export function row(attrs, first, ...cells) {
  return el("tr", attrs, cell("th", first, { scope: "row" }), ...cells.map((c) => cell("td", c)));
}

/** A table named by the heading with id `labelId`; `headers` are cells as for row(). */
export function table(labelId, headers, rows) {
  return el("table", { class: "grid", "aria-labelledby": labelId },
    el("thead", {}, el("tr", {}, ...headers.map((h) => cell("th", h, { scope: "col" })))), el("tbody", {}, ...rows));
}

export function heading(id, text) {
  return el("h3", { class: "table-title", id }, text);
}

export function svg(tag, attrs = {}) {
  const node = document.createElementNS(SVG_NS, tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  return node;
}

export function badge(status, id) {
  return el("span", { class: `badge badge-${status}`, id }, inWords(status));
}

/** A status as a person reads it: "screened_out" → "screened out". */
export function inWords(status) {
  return String(status).replaceAll("_", " ");
}

/** "3 active · 12 completed · 1 screened out" in the order a study's flow goes. */
export function countsText(counts) {
  const order = ["active", "completed", "declined", "screened_out", "abandoned", "withdrawn"];
  const known = order.filter((s) => counts[s]).map((s) => `${counts[s]} ${inWords(s)}`);
  const other = Object.keys(counts).filter((s) => !order.includes(s)).map((s) => `${counts[s]} ${inWords(s)}`);
  const parts = [...known, ...other];
  return parts.length ? parts.join(" · ") : "no participants yet";
}

/** " · 2 preview sessions" (not counted among the participants), or "" without any. */
export function previewText(n) {
  return n ? ` · ${n} preview session${n === 1 ? "" : "s"}` : "";
}

export function showError(element, what, err) {
  element.textContent = describe(what, err);
}

export function focusHeading(heading) {
  heading.focus({ preventScroll: false });
}

/** Update a node's text only when it changed (keeps selections and screen readers calm). */
export function setText(node, text) {
  if (node.textContent !== text) node.textContent = text;
}

export function ago(seconds) {
  if (seconds < 5) return "just now";
  if (seconds < 90) return `${Math.round(seconds)} s ago`;
  if (seconds < 90 * 60) return `${Math.round(seconds / 60)} min ago`;
  if (seconds < 36 * 3600) return `${Math.round(seconds / 3600)} h ago`;
  return `${Math.round(seconds / 86400)} d ago`;
}

export function number(value, digits = 2) {
  if (value === null || value === undefined || Number.isNaN(value)) return "–";
  return value.toFixed(digits);
}

const SPARK_W = 96;
const SPARK_H = 24;

/**
 * A small line of the belief that trust is high after each scored trial (0 at the bottom, 1 at
 * the top, a dotted line at 0.5), its last point marked.
 */
export function sparkline(history) {
  const chart = svg("svg", { class: "sparkline", width: SPARK_W, height: SPARK_H, viewBox: `0 0 ${SPARK_W} ${SPARK_H}`,
    role: "img" });
  const last = history[history.length - 1];
  const title = svg("title");
  title.textContent = history.length
    ? `Belief that trust is high after each of ${history.length} scored trials; now ${last.toFixed(2)}`
    : "No scored trial yet";
  chart.setAttribute("aria-label", title.textContent);
  chart.append(title, svg("line", { class: "mid", x1: 0, x2: SPARK_W, y1: SPARK_H / 2, y2: SPARK_H / 2 }));
  if (!history.length) return chart;
  const pad = 2;
  const x = (i) => pad + (history.length === 1 ? 0 : (i * (SPARK_W - 2 * pad)) / (history.length - 1));
  const y = (b) => pad + (1 - b) * (SPARK_H - 2 * pad);
  const points = history.map((b, i) => `${x(i).toFixed(1)},${y(b).toFixed(1)}`).join(" ");
  chart.append(svg("polyline", { class: "line", points }),
    svg("circle", { class: "dot", cx: x(history.length - 1).toFixed(1), cy: y(last).toFixed(1), r: 2.2 }));
  return chart;
}
