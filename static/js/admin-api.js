// The admin API over fetch with the admin token as a bearer header. The token lives in this
// tab's sessionStorage only. Errors carry the server's reason (ApiError.detail); a 401 logs out.

import { ApiError } from "./api.js";

const TOKEN_KEY = "trustlab.admin-token";
const LOGOUT_REASON_KEY = "trustlab.admin-logout-reason";

export const token = {
  get: () => sessionStorage.getItem(TOKEN_KEY),
  set: (value) => sessionStorage.setItem(TOKEN_KEY, value),
  clear: () => sessionStorage.removeItem(TOKEN_KEY),
};

/** Why the experimenter was last logged out, kept in the tab until the next log-in (a reload still says it). */
export const loggedOutBecause = {
  get: () => sessionStorage.getItem(LOGOUT_REASON_KEY) || "",
  set: (message) => (message ? sessionStorage.setItem(LOGOUT_REASON_KEY, message)
    : sessionStorage.removeItem(LOGOUT_REASON_KEY)),
};

/** "what failed: the server's reason (HTTP status)" for an error shown to the experimenter. */
export function describe(what, err) {
  if (err instanceof ApiError) {
    const status = err.status ? ` (HTTP ${err.status})` : "";
    return `${what}: ${err.detail}${status}`;
  }
  return `${what}: ${err && err.message ? err.message : err}`;
}

export class AdminApi {
  /** onUnauthorized(detail) when the server refuses the token; onTrouble(bool) for the connection notice. */
  constructor({ onUnauthorized = () => {}, onTrouble = () => {} } = {}) {
    this.onUnauthorized = onUnauthorized;
    this.onTrouble = onTrouble;
  }

  /** One request (no retries: the caller shows the error). Resolves to parsed JSON, or the Response with raw.
   * Cookies are neither sent nor stored, except with credentials "same-origin" (the report-reading cookie).
   * loggingIn: a token being tried, not the session's: its 401 is the caller's to show (no log-out). */
  async request(method, path, { body, raw = false, bearer = token.get(), credentials = "omit", loggingIn = false } = {}) {
    const headers = { Accept: raw ? "*/*" : "application/json", Authorization: `Bearer ${bearer || ""}` };
    const init = { method, headers, cache: "no-store", credentials };
    if (body !== undefined) {
      headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(body);
    }
    let response;
    try {
      response = await fetch(path, init);
    } catch (_err) {
      this.onTrouble(true);
      throw new ApiError(0, "the server could not be reached (is trustlab serve still running?)");
    }
    this.onTrouble(false);
    if (!response.ok) {
      let data = {};
      try {
        data = await response.json();
      } catch (_err) {
        data = {};
      }
      const error = new ApiError(response.status, data.detail || `${method} ${path} failed`, data);
      if (response.status === 401 && !loggingIn) this.onUnauthorized(error.detail);
      throw error;
    }
    if (raw) return response;
    return response.status === 204 ? {} : response.json();
  }

  get(path) {
    return this.request("GET", path);
  }

  post(path, body = {}) {
    return this.request("POST", path, { body });
  }

  /** GET a file with the bearer header; resolves to { blob, filename }. */
  async fetchFile(path, fallbackName) {
    const response = await this.request("GET", path, { raw: true });
    const disposition = response.headers.get("Content-Disposition") || "";
    const match = /filename="([^"]+)"/.exec(disposition);
    return { blob: await response.blob(), filename: match ? match[1] : fallbackName };
  }

  /** Download a file through a Blob URL (a plain link cannot send the bearer header). */
  async download(path, fallbackName) {
    const { blob, filename } = await this.fetchFile(path, fallbackName);
    const url = URL.createObjectURL(blob);
    const link = document.createElement("a");
    link.href = url;
    link.download = filename;
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60000);
    return filename;
  }
}
