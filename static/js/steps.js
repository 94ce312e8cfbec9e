// Pages between the study's parts: the one that ends the practice (phase practice_done) and the final score on the
// debrief. Everything said comes from the state (the study's config), never a literal of this page.

import { describeOutcome } from "./trial.js";

const $ = (id) => document.getElementById(id);

/** Seconds as a person reads them: "4 seconds", "2.5 seconds", "1 second". */
export function seconds(value) {
  const n = Math.round(value * 100) / 100;
  return `${n} ${n === 1 ? "second" : "seconds"}`;
}

/** A score with its sign where it is below zero: "23 points", "−4 points", "1 point". */
export function pointsText(score) {
  const n = Math.round(score * 10) / 10;
  const text = `${n < 0 ? "−" : ""}${Math.abs(n)}`;
  return `${text} ${Math.abs(n) === 1 ? "point" : "points"}`;
}

/** "Robot A", "Robot A and Robot B", "Robot A, Robot B and Robot C". */
function listed(names) {
  return names.length < 2 ? names.join("") : `${names.slice(0, -1).join(", ")} and ${names[names.length - 1]}`;
}

/** The page after the last practice trial: the practice is over, choices count, and how long the window is. */
export function renderPracticeDone(state) {
  const part = state.scored_part;
  const last = state.last_trial;
  $("practice-done-last").hidden = !(last && last.practice);
  $("practice-done-last").textContent = last && last.practice ? `Last practice item: ${describeOutcome(last)[0]}` : "";
  const robots = part.robots.length === 1 ? `You now supervise ${part.robots[0]}`
    : `You now supervise ${part.robots.length} robots, one after the other: ${listed(part.robots)}`;
  $("practice-done-robots").textContent = `${robots} (${part.n_trials} items in all). There are no more hints.`;
  $("practice-done-window").replaceChildren(
    "When the robot says it will collect an item by itself, you have ",
    Object.assign(document.createElement("strong"), { textContent: seconds(part.decision_window_s) }),
    " to press ",
    Object.assign(document.createElement("strong"), { textContent: "Intervene" }),
    " (or ", Object.assign(document.createElement("kbd"), { textContent: "Space" }),
    ") and collect it yourself. If you do not, the robot tries by itself.",
  );
  $("practice-done-points").hidden = !part.plays_for_points;
  $("practice-done-points").textContent = "Every item now scores points, as the instructions said (the practice "
    + `items did not): your score so far is ${pointsText(state.score)}.`;
  $("practice-done-continue").disabled = false;
}

/** On the debrief, the final score of a study that plays for points (the state's final_score; null: none). */
export function renderFinalScore(state) {
  const score = state.final_score;
  $("final-score").hidden = score === null || score === undefined;
  $("final-score").textContent = $("final-score").hidden ? "" : `Your final score: ${pointsText(score)}.`;
}
