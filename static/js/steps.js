// Pages between the study's parts: the one that ends the practice (phase practice_done) and the final score on the
// debrief. Everything said comes from the state (the study's config), never a literal of this page.

import { setRich, t, tn } from "./i18n.js";
import { describeOutcome } from "./trial.js";

const $ = (id) => document.getElementById(id);

/** Seconds as a person reads them: "4 seconds", "2.5 seconds", "1 second". */
export function seconds(value) {
  return tn("units.seconds", Math.round(value * 100) / 100);
}

/** A score with its sign where it is below zero: "23 points", "−4 points", "1 point". */
export function pointsText(score) {
  const n = Math.round(score * 10) / 10;
  return n < 0 ? tn("units.points_negative", Math.abs(n)) : tn("units.points", n);
}

/** "Robot A", "Robot A and Robot B", "Robot A, Robot B and Robot C" (the language's own way of listing). */
function listed(names) {
  return new Intl.ListFormat(document.documentElement.lang || "en", { style: "long", type: "conjunction" })
    .format(names);
}

/** The page after the last practice trial: the practice is over, choices count, and how long the window is. */
export function renderPracticeDone(state) {
  const part = state.scored_part;
  const last = state.last_trial;
  $("practice-done-last").hidden = !(last && last.practice);
  $("practice-done-last").textContent = last && last.practice
    ? t("practice_done.last", { outcome: describeOutcome(last)[0] }) : "";
  const robots = part.robots.length === 1 ? t("practice_done.robot", { robot: part.robots[0] })
    : t("practice_done.robots", { count: part.robots.length, robots: listed(part.robots) });
  $("practice-done-robots").textContent = tn("practice_done.items", part.n_trials, { robots });
  setRich($("practice-done-window"), t("practice_done.window", { seconds: seconds(part.decision_window_s) }));
  $("practice-done-points").hidden = !part.plays_for_points;
  $("practice-done-points").textContent = t("practice_done.points", { score: pointsText(state.score) });
  $("practice-done-continue").disabled = false;
}

/** On the debrief, the final score of a study that plays for points (the state's final_score; null: none). */
export function renderFinalScore(state) {
  const score = state.final_score;
  $("final-score").hidden = score === null || score === undefined;
  $("final-score").textContent = $("final-score").hidden ? "" : t("debrief.final_score", { score: pointsText(score) });
}
