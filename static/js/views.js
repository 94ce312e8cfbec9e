// The non-trial screens: consent, instructions, questionnaires, debrief and the end pages.
// Each render is a no-op when the same step is already on screen, so polling never wipes
// answers being filled in.

import { N_, t, tn } from "./i18n.js";

const $ = (id) => document.getElementById(id);
const REDIRECT_AFTER_S = 8;

/** Text with blank lines as paragraphs (textContent only: nothing from the server is HTML). */
export function setProse(element, text) {
  element.replaceChildren(...(text || "").split(/\n\s*\n/).filter((p) => p.trim()).map((p) => {
    const para = document.createElement("p");
    para.textContent = p.trim();
    return para;
  }));
}

/** "This study takes about 10–20 minutes." where the state says how long (consent and instructions). */
function showDuration(element, state, sentence) {
  element.hidden = !state.duration;
  element.textContent = state.duration ? sentence(state.duration.text) : "";
}

export function renderConsent(state) {
  setProse($("consent-text"), state.text);
  showDuration($("consent-duration"), state, (text) => t("consent.duration", { duration: text }));
  showDeclineConfirm(false);
}

/** "I do not agree" first asks again; only "Yes" ends the session. */
export function showDeclineConfirm(shown) {
  $("decline-confirm").hidden = !shown;
  $("consent-actions").hidden = shown;
  if (shown) $("decline-question").focus();
}

export function renderInstructions(state) {
  setProse($("instructions-text"), state.text);
  showDuration($("instructions-duration"), state, (text) => t("instructions.duration", { duration: text }));
  $("video-row").hidden = !state.video_url;
  if (state.video_url) $("video-link").href = state.video_url;
  const practice = state.step && state.step.phase === "instructions";
  $("instructions-done").textContent = practice ? t("instructions.to_practice") : t("common.continue");
  $("howto-limit").textContent = duration(teleopTimeLimit(state));
  const tutorial = state.tutorial || null;
  $("howto-tutorial").hidden = !tutorial;
  if (tutorial) {
    $("howto-tries").textContent = tn("howto.tries", tutorial.max_tries, { each: duration(tutorial.time_limit_s) });
  }
}

/** The scored teleoperation time limit (s): top level of the state, or its timing block (older servers). */
export function teleopTimeLimit(state) {
  return state.teleop_time_limit_s ?? (state.timing && state.timing.teleop_time_limit_s) ?? null;
}

/** Seconds in words: "45 seconds", "2 minutes", "1 minute 30 seconds". */
export function duration(seconds) {
  if (seconds === null || seconds === undefined) return t("units.limited_time");
  const s = Math.round(seconds);
  if (s < 120) return tn("units.seconds", s);
  const m = Math.floor(s / 60);
  const minutes = tn("units.minutes", m);
  return s % 60 ? t("units.minutes_seconds", { minutes, seconds: tn("units.seconds", s % 60) }) : minutes;
}

// -- questionnaires ----------------------------------------------------------------------

function number(value) {
  return Number.isInteger(value) ? String(value) : String(Math.round(value * 1000) / 1000);
}

function scalePoints(scale) {
  const n = Math.round((scale.max - scale.min) / scale.step);
  return Array.from({ length: n + 1 }, (_, i) => Math.round((scale.min + i * scale.step) * 1e9) / 1e9);
}

/** An item's fieldset: its question as the legend ("(optional)" when it may be left out), then its answer. */
function itemFieldset(q, item, index, points) {
  const fieldset = document.createElement("fieldset");
  fieldset.className = `scale-item item-${item.kind || "rating"}`;
  fieldset.dataset.item = item.id;
  const legend = document.createElement("legend");
  legend.id = `item-${item.id}-question`;
  legend.textContent = `${index + 1}. ${item.text}`;
  if (item.required === false) {
    const optional = document.createElement("span");
    optional.className = "optional";
    optional.textContent = ` ${t("survey.optional")}`;
    legend.append(optional);
  }
  fieldset.append(legend);
  if (item.kind === "text") fieldset.append(...textAnswer(item, legend.id));
  else if (item.kind === "choice") fieldset.append(choiceList(item));
  else fieldset.append(scaleRow(q, item, points));
  return fieldset;
}

function radio(item, value, ...content) {
  const label = document.createElement("label");
  const input = document.createElement("input");
  Object.assign(input, { type: "radio", name: item.id, value, required: item.required !== false });
  label.append(input, ...content);
  return label;
}

function scaleRow(q, item, points) {
  const row = document.createElement("div");
  row.className = "scale-row";
  const anchors = q.scale.anchors || {};
  for (const value of points) {
    const text = document.createElement("span");
    text.className = "point";
    text.textContent = q.scale.unit ? `${number(value)} ${q.scale.unit}` : number(value);
    const label = radio(item, String(value), text);
    const anchor = anchors[String(value)] ?? anchors[value];
    if (anchor) {
      const span = document.createElement("span");
      span.className = "anchor";
      span.textContent = anchor;
      label.append(span);
    }
    row.append(label);
  }
  return row;
}

/** One radio button per option, one under the other (arrow keys move between them, as for any radio group). */
function choiceList(item) {
  const list = document.createElement("div");
  list.className = "choice-list";
  for (const option of item.options || []) {
    const text = document.createElement("span");
    text.textContent = option.label;
    list.append(radio(item, option.value, text));
  }
  return list;
}

/** A text area with its limit on screen: "120 of 2000 characters" under it, updated as the participant types. */
function textAnswer(item, questionId) {
  const area = document.createElement("textarea");
  const countId = `item-${item.id}-count`;
  Object.assign(area, { name: item.id, rows: 4, maxLength: item.max_length, required: item.required !== false });
  area.setAttribute("aria-labelledby", questionId);
  area.setAttribute("aria-describedby", countId);
  const count = document.createElement("p");
  count.className = "char-count";
  count.id = countId;
  const update = () => { count.textContent = tn("survey.characters", item.max_length, { used: area.value.length }); };
  area.addEventListener("input", update);
  area.updateCount = update;
  update();
  return [area, count];
}

export function surveyKey(state) {
  return `${state.questionnaire.id}|${state.questionnaire.context}`;
}

export function renderSurvey(state, lastText) {
  const q = state.questionnaire;
  // The questionnaire's texts may be in another language than the page's (it has no translation for the participant's).
  for (const id of ["survey-heading", "survey-instructions", "survey-items"]) $(id).lang = q.language || "";
  $("survey-heading").textContent = q.title;
  $("survey-about").hidden = !q.about;
  $("survey-about").textContent = q.about || "";
  $("survey-instructions").textContent = q.instructions;
  $("survey-last").hidden = !lastText;
  $("survey-last").textContent = lastText || "";
  $("survey-error").replaceChildren();
  const points = q.scale ? scalePoints(q.scale) : [];
  $("survey-items").replaceChildren(...q.items.map((item, i) => itemFieldset(q, item, i, points)));
  for (const item of q.items) restoreAnswer(item, (q.draft || {})[item.id]); // the answers given before a reload
  $("survey-submit").disabled = false;
}

function restoreAnswer(item, value) {
  if (value === undefined || value === null) return;
  const form = $("survey-form");
  const name = CSS.escape(item.id);
  if (item.kind === "text") {
    const area = form.querySelector(`textarea[name="${name}"]`);
    area.value = value;
    area.updateCount();
    return;
  }
  const shown = item.kind === "choice" ? String(value) : number(value);
  const input = form.querySelector(`input[name="${name}"][value="${CSS.escape(shown)}"]`);
  if (input) input.checked = true;
}

/** The item's answer on the page, or undefined when it has none yet (blank text counts as none). */
function answerOf(form, item) {
  if (item.kind === "text") {
    const text = form.querySelector(`textarea[name="${CSS.escape(item.id)}"]`).value.trim();
    return text ? text : undefined;
  }
  const checked = form.querySelector(`input[name="${CSS.escape(item.id)}"]:checked`);
  if (!checked) return undefined;
  return item.kind === "choice" ? checked.value : Number(checked.value);
}

/** The answers given so far on the page (for the draft). */
export function answersSoFar(state) {
  const form = $("survey-form");
  const answers = {};
  for (const item of state.questionnaire.items) {
    const value = answerOf(form, item);
    if (value !== undefined) answers[item.id] = value;
  }
  return answers;
}

/** Whether anything is answered on the questionnaire page on screen (read from the page itself: the state may
 * already be the next page's). */
export function anythingAnswered() {
  const form = $("survey-form");
  return Boolean(form.querySelector("input:checked"))
    || [...form.querySelectorAll("textarea")].some((area) => area.value.trim());
}

/** The answers, or the required items left unanswered (marked, with a message, the first focused). */
export function collectAnswers(state) {
  const form = $("survey-form");
  const answers = {};
  const missing = [];
  state.questionnaire.items.forEach((item, i) => {
    const value = answerOf(form, item);
    const fieldset = form.querySelector(`fieldset[data-item="${CSS.escape(item.id)}"]`);
    const unanswered = value === undefined && item.required !== false;
    fieldset.classList.toggle("missing", unanswered);
    if (unanswered) fieldset.setAttribute("aria-invalid", "true");
    else fieldset.removeAttribute("aria-invalid");
    if (value !== undefined) answers[item.id] = value;
    if (unanswered) missing.push({ index: i + 1, fieldset });
  });
  if (missing.length === 0) {
    $("survey-error").replaceChildren();
    return { answers, missing };
  }
  const numbers = missing.map((m) => m.index).join(", ");
  $("survey-error").textContent = missing.length === 1
    ? t("survey.missing_one", { number: numbers })
    : tn("survey.missing_many", missing.length, { numbers });
  missing[0].fieldset.querySelector("input, textarea").focus();
  return { answers, missing };
}

// -- completion codes, debrief and end pages ------------------------------------------------

export async function copyText(code, status) {
  try {
    await navigator.clipboard.writeText(code.textContent);
  } catch (_err) {
    const range = document.createRange(); // no clipboard API (e.g. plain http): select it instead
    range.selectNodeContents(code);
    getSelection().removeAllRanges();
    getSelection().addRange(range);
    status.textContent = t("code.selected");
    return;
  }
  status.textContent = t("code.copied");
}

export function wireCopy(buttonId, codeId, statusId) {
  $(buttonId).addEventListener("click", () => copyText($(codeId), $(statusId)));
}

let redirectTimer = null;

export function cancelRedirect() {
  clearInterval(redirectTimer);
  redirectTimer = null;
  $("redirect-countdown").textContent = t("debrief.redirect_cancelled");
  $("redirect-stay").hidden = true;
}

function startRedirect(url) {
  let left = REDIRECT_AFTER_S;
  const show = () => {
    $("redirect-countdown").textContent = t("debrief.redirect_in", { seconds: left });
  };
  show();
  clearInterval(redirectTimer);
  redirectTimer = setInterval(() => {
    left -= 1;
    if (left > 0) return show();
    clearInterval(redirectTimer);
    location.assign(url);
  }, 1000);
}

export function renderDebrief(state) {
  setProse($("debrief-text"), state.text);
  const completion = state.completion || {};
  $("completion-code").textContent = completion.code || "";
  const pay = completion.compensation;
  $("compensation").hidden = pay === null || pay === undefined;
  if (!$("compensation").hidden) {
    $("compensation").textContent = t("debrief.payment", { amount: pay.toFixed(2), currency: completion.currency || "" })
      .trim();
  }
  $("redirect").hidden = !completion.redirect_url;
  if (completion.redirect_url && state.preview) {
    // The experimenter trying the study sees the link a participant would be sent to, and stays here.
    $("redirect-link").href = completion.redirect_url;
    $("redirect-stay").hidden = true;
    $("redirect-countdown").textContent = t("debrief.preview_redirect");
  } else if (completion.redirect_url) {
    $("redirect-link").href = completion.redirect_url;
    $("redirect-stay").hidden = false;
    // Only once the code is on screen: two animation frames make sure it has been painted.
    requestAnimationFrame(() => requestAnimationFrame(() => startRedirect(completion.redirect_url)));
  }
}

/** Each end page's heading and text (catalogue keys). */
const END_TEXTS = {
  declined: [N_("end.declined.title"), N_("end.declined.text")],
  abandoned: [N_("end.abandoned.title"), N_("end.abandoned.text")],
  screened_out: [N_("end.screened_out.title"), N_("end.screened_out.text")],
  withdrawn: [N_("end.withdrawn.title"), N_("end.withdrawn.text")],
  invalid: [N_("end.invalid.title"), N_("end.invalid.text")],
  closed: [N_("end.closed.title"), N_("end.closed.text")],
  finished: [N_("end.finished.title"), N_("end.finished.text")],
};

export function renderEnd(kind, state) {
  const [title, text] = END_TEXTS[kind] || END_TEXTS.finished;
  $("end-heading").textContent = t(title);
  $("end-text").textContent = t(text);
  const completion = state && state.completion;
  $("end-code").hidden = !completion;
  if (completion) {
    // An outcome may have a redirect without a code (e.g. a timed-out session of a study that gives none).
    $("end-code-label").hidden = $("end-code-row").hidden = !completion.code;
    $("end-code-value").textContent = completion.code || "";
    $("end-redirect").hidden = !completion.redirect_url;
    if (completion.redirect_url) $("end-redirect-link").href = completion.redirect_url;
  }
}
