// The participant API over fetch: JSON in and out, an Idempotency-Key per user action
// (reused on every retry of that action), and retries with backoff on network errors and
// 5xx/429 while a "reconnecting…" notice is shown. 4xx errors are returned to the caller.

import { N_, t } from "./i18n.js";

const MIN_DELAY_MS = 500;
const MAX_DELAY_MS = 8000;

export class ApiError extends Error {
  constructor(status, detail, body) {
    super(detail || String(status));
    this.status = status;
    this.detail = detail || "";
    this.body = body || {};
  }
}

/** A fresh random key for one user action (works without a secure context, unlike randomUUID). */
export function newKey() {
  const bytes = new Uint8Array(16);
  crypto.getRandomValues(bytes);
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

export const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function retryable(status) {
  return status >= 500 || status === 429 || status === 408;
}

/** Whether an answer's JSON body names one of `codes` (read from a copy: the body stays readable). */
async function hasCode(response, codes) {
  if (!codes.length) return false;
  try {
    return codes.includes((await response.clone().json()).code);
  } catch (_err) {
    return false;
  }
}

export class Api {
  /** onTrouble(true) when a request has to be retried, onTrouble(false) once one gets through. */
  constructor({ onTrouble = () => {} } = {}) {
    this.onTrouble = onTrouble;
    this.troubled = false;
  }

  _setTrouble(value) {
    if (value !== this.troubled) {
      this.troubled = value;
      this.onTrouble(value);
    }
  }

  /**
   * One request; with `retry` it is repeated until it gets an answer that is not a network
   * error or 5xx/429, with the same Idempotency-Key each time. An error answer whose body's
   * `code` is in `finalCodes` (e.g. a full study's 503 "study_full") is the server's considered
   * answer, not trouble: it is thrown as an ApiError at once instead of retried.
   */
  async request(method, path, { body, key, retry = true, keepalive = false, finalCodes = [] } = {}) {
    const headers = { Accept: "application/json" };
    if (body !== undefined) headers["Content-Type"] = "application/json";
    if (key) headers["Idempotency-Key"] = key;
    const init = { method, headers, cache: "no-store", credentials: "same-origin", keepalive };
    if (body !== undefined) init.body = JSON.stringify(body);
    let delay = MIN_DELAY_MS;
    for (;;) {
      let response;
      try {
        response = await fetch(path, init);
      } catch (err) {
        if (!retry) {
          this._setTrouble(true);
          throw err;
        }
        this._setTrouble(true);
        await sleep(delay);
        delay = Math.min(delay * 2, MAX_DELAY_MS);
        continue;
      }
      if (retry && retryable(response.status) && !(await hasCode(response, finalCodes))) {
        this._setTrouble(true);
        await sleep(delay);
        delay = Math.min(delay * 2, MAX_DELAY_MS);
        continue;
      }
      this._setTrouble(false);
      let data = {};
      try {
        data = await response.json();
      } catch (_err) {
        data = {};
      }
      if (!response.ok) throw new ApiError(response.status, data.detail, data);
      return data;
    }
  }
}

/** Shows and hides the "reconnecting…" notice. */
export function connectionNotice(element) {
  return (trouble) => {
    element.hidden = !trouble;
    element.textContent = trouble ? t("connection.lost") : "";
  };
}

/** An error answer in the participant's words: the server names the sentence by its catalogue key (``message``,
 * server/errors.py), never in English; an answer without one (a proxy's) gets a general sentence. */
export function errorText(err) {
  const body = err.body || {};
  return t(body.message || N_("errors.unknown"), { ...(body.message_params || {}), status: err.status });
}
