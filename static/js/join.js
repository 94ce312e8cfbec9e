// /join/{slug}?PROLIFIC_PID=…: join the study, then go to the participant's page with
// location.replace, so that Back never returns here (and never joins twice).

import { Api, ApiError, connectionNotice } from "./api.js";

const heading = document.getElementById("join-heading");
const message = document.getElementById("join-message");
const retryRow = document.getElementById("join-retry-row");
const retryButton = document.getElementById("join-retry");

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
  const text = "Please try again in a few minutes: a place opens as soon as another participant finishes.";
  if (!again) return text;
  const time = new Date().toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" });
  return `${text} It was still full at ${time}.`;
}

async function join(again = false) {
  const slug = decodeURIComponent(location.pathname.split("/")[2] || "");
  const api = new Api({ onTrouble: connectionNotice(document.getElementById("connection")) });
  const query = location.search;
  try {
    const key = resumeKey(slug);
    const joined = await api.request("POST", `/api/studies/${encodeURIComponent(slug)}/join${query}`,
      { body: key ? { resume_key: key } : {}, finalCodes: [STUDY_FULL, ADDRESS_BUSY] });
    location.replace(`/p/${encodeURIComponent(joined.token)}`);
  } catch (err) {
    if (!(err instanceof ApiError)) throw err;
    if (err.body.code === STUDY_FULL) {
      show("This study is full right now", fullText(again), { retry: true });
    } else if (err.body.code === ADDRESS_BUSY) {
      const wait = err.body.retry_after_s || 60;
      const when = wait < 90 ? `${wait} seconds` : `about ${Math.round(wait / 60)} minutes`;
      show("Please wait a moment", "Many people on your network have just joined this study and not started yet. "
        + `Please try again in ${when}.`, { retry: true });
    } else if (err.body.code === NOT_OPEN) {
      show("This study has not started yet", "The researchers have not opened this study to participants yet. "
        + "Please come back later, or check the link and the start time you were given.");
    } else if (err.status === 404) {
      show("Study not found", "There is no study at this address. Please check the link you were given.");
    } else if (err.status === 410) {
      show("This study is closed", "This study is not taking new participants any more. Thank you for your interest.");
    } else {
      show("Could not join the study", err.detail || `The server refused the request (status ${err.status}).`);
    }
  }
}

retryButton.addEventListener("click", () => {
  retryButton.disabled = true;
  message.textContent = "Joining the study…";
  join(true);
});

join();
