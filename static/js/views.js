// The non-trial screens: consent, instructions, questionnaires, debrief and the end pages.
// Each render is a no-op when the same step is already on screen, so polling never wipes
// answers being filled in.

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
  showDuration($("consent-duration"), state, (text) => `The study takes ${text} in all.`);
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
  showDuration($("instructions-duration"), state,
    (text) => `All in all, the study takes ${text}.`);
  $("video-row").hidden = !state.video_url;
  if (state.video_url) $("video-link").href = state.video_url;
  const practice = state.step && state.step.phase === "instructions";
  $("instructions-done").textContent = practice ? "Continue to the practice" : "Continue";
  $("howto-limit").textContent = duration(teleopTimeLimit(state));
  const tutorial = state.tutorial || null;
  $("howto-tutorial").hidden = !tutorial;
  if (tutorial) {
    $("howto-tries").textContent = ` (up to ${tutorial.max_tries} ${tutorial.max_tries === 1 ? "try" : "tries"} of `
      + `${duration(tutorial.time_limit_s)} each)`;
  }
}

/** The scored teleoperation time limit (s): top level of the state, or its timing block (older servers). */
export function teleopTimeLimit(state) {
  return state.teleop_time_limit_s ?? (state.timing && state.timing.teleop_time_limit_s) ?? null;
}

/** Seconds in words: "45 seconds", "2 minutes", "1 minute 30 seconds". */
export function duration(seconds) {
  if (seconds === null || seconds === undefined) return "a limited time";
  const s = Math.round(seconds);
  const unit = (n, word) => `${n} ${word}${n === 1 ? "" : "s"}`;
  if (s < 120) return unit(s, "second");
  const m = Math.floor(s / 60);
  return s % 60 ? `${unit(m, "minute")} ${unit(s % 60, "second")}` : unit(m, "minute");
}

// -- questionnaires ----------------------------------------------------------------------

function number(value) {
  return Number.isInteger(value) ? String(value) : String(Math.round(value * 1000) / 1000);
}

function scalePoints(scale) {
  const n = Math.round((scale.max - scale.min) / scale.step);
  return Array.from({ length: n + 1 }, (_, i) => Math.round((scale.min + i * scale.step) * 1e9) / 1e9);
}

function itemFieldset(q, item, index, points) {
  const fieldset = document.createElement("fieldset");
  fieldset.className = "scale-item";
  fieldset.dataset.item = item.id;
  const legend = document.createElement("legend");
  legend.textContent = `${index + 1}. ${item.text}`;
  fieldset.append(legend);
  const row = document.createElement("div");
  row.className = "scale-row";
  const anchors = q.scale.anchors || {};
  for (const value of points) {
    const label = document.createElement("label");
    const input = document.createElement("input");
    Object.assign(input, { type: "radio", name: item.id, value: String(value), required: true });
    const text = document.createElement("span");
    text.className = "point";
    text.textContent = q.scale.unit ? `${number(value)} ${q.scale.unit}` : number(value);
    label.append(input, text);
    const anchor = anchors[String(value)] ?? anchors[value];
    if (anchor) {
      const span = document.createElement("span");
      span.className = "anchor";
      span.textContent = anchor;
      label.append(span);
    }
    row.append(label);
  }
  fieldset.append(row);
  return fieldset;
}

export function surveyKey(state) {
  return `${state.questionnaire.id}|${state.questionnaire.context}`;
}

export function renderSurvey(state, lastText) {
  const q = state.questionnaire;
  $("survey-heading").textContent = q.title;
  $("survey-about").hidden = !q.about;
  $("survey-about").textContent = q.about || "";
  $("survey-instructions").textContent = q.instructions;
  $("survey-last").hidden = !lastText;
  $("survey-last").textContent = lastText || "";
  $("survey-error").replaceChildren();
  const points = scalePoints(q.scale);
  $("survey-items").replaceChildren(...q.items.map((item, i) => itemFieldset(q, item, i, points)));
  for (const [itemId, value] of Object.entries(q.draft || {})) { // the answers given before a reload
    const input = $("survey-form").querySelector(`input[name="${CSS.escape(itemId)}"][value="${number(value)}"]`);
    if (input) input.checked = true;
  }
  $("survey-submit").disabled = false;
}

function checkedInput(form, item) {
  return form.querySelector(`input[name="${CSS.escape(item.id)}"]:checked`);
}

/** The answers given so far on the page (for the draft). */
export function answersSoFar(state) {
  const form = $("survey-form");
  const answers = {};
  for (const item of state.questionnaire.items) {
    const checked = checkedInput(form, item);
    if (checked) answers[item.id] = Number(checked.value);
  }
  return answers;
}

/** The answers, or the fieldsets left unanswered (marked, with a message, the first focused). */
export function collectAnswers(state) {
  const form = $("survey-form");
  const answers = {};
  const missing = [];
  state.questionnaire.items.forEach((item, i) => {
    const checked = checkedInput(form, item);
    const fieldset = form.querySelector(`fieldset[data-item="${CSS.escape(item.id)}"]`);
    fieldset.classList.toggle("missing", !checked);
    if (checked) fieldset.removeAttribute("aria-invalid");
    else fieldset.setAttribute("aria-invalid", "true");
    if (checked) answers[item.id] = Number(checked.value);
    else missing.push({ index: i + 1, fieldset });
  });
  if (missing.length === 0) {
    $("survey-error").replaceChildren();
    return { answers, missing };
  }
  const numbers = missing.map((m) => m.index).join(", ");
  $("survey-error").textContent = missing.length === 1
    ? `Please answer question ${numbers} before you continue.`
    : `Please answer every question before you continue: ${missing.length} are missing (questions ${numbers}).`;
  missing[0].fieldset.querySelector("input").focus();
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
    status.textContent = "Selected: press Ctrl+C (⌘C) to copy.";
    return;
  }
  status.textContent = "Copied.";
}

export function wireCopy(buttonId, codeId, statusId) {
  $(buttonId).addEventListener("click", () => copyText($(codeId), $(statusId)));
}

let redirectTimer = null;

export function cancelRedirect() {
  clearInterval(redirectTimer);
  redirectTimer = null;
  $("redirect-countdown").textContent = "You can use the link above whenever you are ready.";
  $("redirect-stay").hidden = true;
}

function startRedirect(url) {
  let left = REDIRECT_AFTER_S;
  const show = () => {
    $("redirect-countdown").textContent = `Taking you back in ${left} s…`;
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
    $("compensation").textContent = `Your payment: ${pay.toFixed(2)} ${completion.currency || ""}`.trim();
  }
  $("redirect").hidden = !completion.redirect_url;
  if (completion.redirect_url) {
    $("redirect-link").href = completion.redirect_url;
    $("redirect-stay").hidden = false;
    // Only once the code is on screen: two animation frames make sure it has been painted.
    requestAnimationFrame(() => requestAnimationFrame(() => startRedirect(completion.redirect_url)));
  }
}

const END_TEXTS = {
  declined: ["You chose not to take part",
    "Thank you for considering this study. Nothing more is needed; you can close this page."],
  abandoned: ["This session has ended",
    "The session ended because it was inactive for too long. Please contact the researcher if you think this is a mistake."],
  withdrawn: ["This session was withdrawn",
    "The researcher has withdrawn this session. Please contact them if you have questions."],
  invalid: ["This link is not valid",
    "We could not find a session for this link. Please use the exact link you were given."],
  closed: ["This study is closed", "This study is not taking part any more. Thank you for your interest."],
  finished: ["This session is finished", "This session is already finished. Thank you for taking part."],
};

export function renderEnd(kind, state) {
  const [title, text] = END_TEXTS[kind] || END_TEXTS.finished;
  $("end-heading").textContent = title;
  $("end-text").textContent = text;
  const completion = state && state.completion;
  $("end-code").hidden = !completion;
  if (completion) {
    $("end-code-value").textContent = completion.code;
    $("end-redirect").hidden = !completion.redirect_url;
    if (completion.redirect_url) $("end-redirect-link").href = completion.redirect_url;
  }
}
