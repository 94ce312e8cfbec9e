// /join/{slug}?PROLIFIC_PID=…: join the study, then go to the participant's page with
// location.replace, so that Back never returns here (and never joins twice).

import { Api, ApiError, connectionNotice, errorText } from "./api.js";
import { language, loadMessages, t, tn } from "./i18n.js";

const heading = document.getElementById("join-heading");
const message = document.getElementById("join-message");
const retryRow = document.getElementById("join-retry-row");
const retryButton = document.getElementById("join-retry");

/**
 * The join link's parameters (PROLIFIC_PID, SESSION_ID, lang, …), read once; then the address bar, the history
 * and anything that reads the page's URL lose them at once (data minimisation: the recruitment id is in no URL
 * after the join). The join sends them in its body, not in the API's URL (server logs keep URLs).
 */
const JOIN_PARAMS = new URLSearchParams(location.search);
if (location.search) history.replaceState(history.state, "", location.pathname);
const MAX_JOIN_PARAMS = 16; // as the server takes them (JoinCreate.params)

/** A full study (its cap on active participants reached: 503, code study_full) is told, not retried. */
const STUDY_FULL = "study_full";
/** A study that is still being prepared (409, code study_not_open). */
const NOT_OPEN = "study_not_open";
/** Too many people from this network have joined and not yet consented (429, code address_busy): told, not retried. */
const ADDRESS_BUSY = "address_busy";

/**
 * This browser's resume key for the study, made before its first join and kept in localStorage: the same link
 * reopened in this browser (a reload, a closed tab) resumes the session, while the external id alone (PROLIFIC_PID,
 * pid, …) never does. localStorage, not a cookie: the key exists before the first request, so a join retried after
 * a lost answer, or a double click, resumes rather than starting a second session; and the session's own token is
 * in the page's address anyway, so an HttpOnly cookie would protect nothing more.
 */
function resumeKey(slug) {
  const name = `trustlab.resume.${slug}`;
  try {
    let key = localStorage.getItem(name);
    if (!key || !/^[A-Za-z0-9_-]{22,128}$/.test(key)) {
      const bytes = crypto.getRandomValues(new Uint8Array(16)); // 128 bits
      key = btoa(String.fromCharCode(...bytes)).replace(/\+/g, "-").replace(/\//g, "_").replace(/=+$/, "");
      localStorage.setItem(name, key);
    }
    return key;
  } catch {
    return undefined; // storage blocked: the server makes a key; this browser then resumes by the page's link only
  }
}

function show(title, text, { retry = false } = {}) {
  document.title = title;
  heading.textContent = title;
  message.textContent = text;
  message.setAttribute("role", "alert");
  retryRow.hidden = !retry;
  retryButton.disabled = false;
  heading.focus();
}

function fullText(again) {
  if (!again) return t("join.full.text");
  const time = new Date().toLocaleTimeString(language(), { hour: "2-digit", minute: "2-digit" });
  return t("join.full.text_again", { time });
}

/** The join's language: the study's answer for this link and browser (its words load before anything is shown). */
async function chooseLanguage(api, slug) {
  try {
    const lang = JOIN_PARAMS.get("lang");
    const query = lang ? `?${new URLSearchParams({ lang })}` : ""; // the language only: no recruitment id in a URL
    const chosen = await api.request("GET", `/api/studies/${encodeURIComponent(slug)}/language${query}`);
    return chosen.language;
  } catch (err) {
    if (!(err instanceof ApiError)) throw err;
    return navigator.language || "en"; // (a link the server cannot read: the browser's language, else English)
  }
}

async function join(again = false) {
  const slug = decodeURIComponent(location.pathname.split("/")[2] || "");
  const api = new Api({ onTrouble: connectionNotice(document.getElementById("connection")) });
  await loadMessages(await chooseLanguage(api, slug));
  document.title = t("join.joining");
  const params = Object.fromEntries([...JOIN_PARAMS].slice(0, MAX_JOIN_PARAMS));
  try {
    const key = resumeKey(slug);
    const joined = await api.request("POST", `/api/studies/${encodeURIComponent(slug)}/join`,
      { body: key ? { params, resume_key: key } : { params }, finalCodes: [STUDY_FULL, ADDRESS_BUSY] });
    location.replace(`/p/${encodeURIComponent(joined.token)}`);
  } catch (err) {
    if (!(err instanceof ApiError)) throw err;
    if (err.body.code === STUDY_FULL) {
      show(t("join.full.title"), fullText(again), { retry: true });
    } else if (err.body.code === ADDRESS_BUSY) {
      const wait = err.body.retry_after_s || 60;
      const when = wait < 90 ? tn("units.seconds", wait) : tn("units.about_minutes", Math.round(wait / 60));
      show(t("join.busy.title"), t("join.busy.text", { when }), { retry: true });
    } else if (err.body.code === NOT_OPEN) {
      show(t("join.not_open.title"), t("join.not_open.text"));
    } else if (err.status === 404) {
      show(t("join.not_found.title"), t("join.not_found.text"));
    } else if (err.status === 410) {
      show(t("join.closed.title"), t("join.closed.text"));
    } else {
      show(t("join.failed.title"), errorText(err));
    }
  }
}

retryButton.addEventListener("click", () => {
  retryButton.disabled = true;
  message.textContent = t("join.joining");
  join(true);
});

join();
