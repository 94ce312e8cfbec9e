// Client events (decision window opened, presses, camera changes, visibility, disconnects),
// each stamped with performance.now(), sent in batches to POST /api/p/{token}/events.
// The events endpoint takes no Idempotency-Key, so every event carries the page-load id and a
// sequence number: a batch repeated after a lost response can be recognised in the data.

import { ApiError, newKey } from "./api.js";

const FLUSH_DELAY_MS = 2000;
const BATCH = 50; // the server takes at most 100 per request
const HEARTBEAT_MS = 10000;

export class EventLog {
  constructor(api, base) {
    this.api = api;
    this.url = `${base}/events`;
    this.page = newKey().slice(0, 12);
    this.seq = 0;
    this.queue = [];
    this.timer = null;
    this.sending = false;
    this.closed = false;
  }

  log(kind, payload = {}) {
    if (this.closed) return;
    this.seq += 1;
    this.queue.push({ kind, client_time_ms: performance.now(), payload: { ...payload, page: this.page, seq: this.seq } });
    if (this.queue.length >= BATCH) this.flush();
    else if (this.timer === null) this.timer = setTimeout(() => this.flush(), FLUSH_DELAY_MS);
  }

  /** Send what is queued, in order (keepalive: the request may outlive the page). */
  async flush({ keepalive = false } = {}) {
    clearTimeout(this.timer);
    this.timer = null;
    if (this.sending || this.queue.length === 0 || this.closed) return;
    this.sending = true;
    const batch = this.queue.slice(0, BATCH);
    try {
      await this.api.request("POST", this.url, { body: { events: batch }, keepalive });
      this.queue.splice(0, batch.length);
    } catch (err) {
      // 410: the session is over and records no more; 4xx: a bad batch would block the queue forever.
      if (err instanceof ApiError) this.queue.splice(0, batch.length);
      if (err instanceof ApiError && err.status === 410) this.closed = true;
    } finally {
      this.sending = false;
    }
    if (this.queue.length) this.timer = setTimeout(() => this.flush(), 0);
  }

  /** The session records nothing more (withdrawn, abandoned: the server would answer 410): drop what is queued and
   * send nothing from now on. */
  close() {
    clearTimeout(this.timer);
    this.timer = null;
    this.queue = [];
    this.closed = true;
  }

  /** Last chance when the page goes away: one keepalive request, no retry. */
  flushOnExit() {
    if (this.closed || this.sending || this.queue.length === 0) return;
    const batch = this.queue.splice(0, 100);
    this.api.request("POST", this.url, { body: { events: batch }, retry: false, keepalive: true }).catch(() => {});
  }
}

/** POST heartbeat every ~10 s (no retry loop: the next beat is the retry). */
export function startHeartbeat(api, base, onResult) {
  const beat = async () => {
    try {
      await api.request("POST", `${base}/heartbeat`, { body: { client_time_ms: performance.now() }, retry: false });
      onResult(true);
    } catch (err) {
      onResult(err instanceof ApiError ? err : false);
    }
  };
  return setInterval(beat, HEARTBEAT_MS);
}
