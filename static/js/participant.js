// The participant page /p/{token}: always renders what GET /api/p/{token}/state says, polling
// while time passes and after each action. The server is the source of truth, so a reload,
// a reopened tab or a dropped connection simply resumes at the same step.

import { Api, ApiError, connectionNotice, newKey } from "./api.js";
import { EventLog, startHeartbeat } from "./events.js";
import { TrialScreen, describeOutcome } from "./trial.js";
import * as views from "./views.js";

const $ = (id) => document.getElementById(id);
const IDLE_POLL_MS = 30000; // notices a withdrawal or an abandoned session on static pages
const SECTIONS = ["loading", "consent", "instructions", "trial", "survey", "debrief", "end"];
const TERMINAL = ["debrief", "declined", "abandoned", "withdrawn"];

class App {
  constructor() {
    this.token = decodeURIComponent(location.pathname.split("/")[2] || "");
    this.base = `/api/p/${encodeURIComponent(this.token)}`;
    const notice = connectionNotice($("connection"));
    this.api = new Api({ onTrouble: (trouble) => { notice(trouble); this.connectivity(trouble); } });
    this.events = new EventLog(this.api, this.base);
    this.state = null;
    this.section = "loading";
    this.viewKey = null;
    this.issued = 0;
    this.applied = 0;
    this.pollTimer = null;
    this.offlineSince = null;
    this.busy = false;
    window.__trustlab = { state: null, section: "loading", teleop: null, viewer: null, renders: 0 };
    window.__trustlab.events = this.events;
    this.trial = new TrialScreen(this);
    this.wire();
  }

  wire() {
    $("consent-agree").addEventListener("click", () => this.act("consent", { agree: true }));
    $("consent-decline").addEventListener("click", () => this.act("consent", { agree: false }));
    $("instructions-done").addEventListener("click", () => this.act("instructions/done"));
    $("survey-form").addEventListener("submit", (event) => {
      event.preventDefault();
      this.submitSurvey();
    });
    views.wireCopy("copy-code", "completion-code", "copy-status");
    views.wireCopy("end-copy", "end-code-value", "end-copy-status");
    $("redirect-stay").addEventListener("click", () => views.cancelRedirect());
    document.addEventListener("visibilitychange", () => {
      this.events.log("visibility", { state: document.visibilityState });
      if (document.visibilityState === "hidden") this.events.flush({ keepalive: true });
      else this.refresh();
    });
    window.addEventListener("pagehide", () => this.events.flushOnExit());
    window.addEventListener("focus", () => this.events.log("window_focus"));
  }

  start() {
    this.events.log("page_loaded", { path: "participant", width: innerWidth, height: innerHeight });
    this.heartbeat = startHeartbeat(this.api, this.base, (result) => {
      if (result instanceof ApiError && result.status === 410) this.refresh();
    });
    this.refresh();
  }

  connectivity(trouble) {
    if (trouble) {
      this.offlineSince = performance.now();
      this.events.log("disconnected");
    } else if (this.offlineSince !== null) {
      this.events.log("reconnected", { offline_ms: performance.now() - this.offlineSince });
      this.offlineSince = null;
    }
  }

  // -- state ---------------------------------------------------------------------------
  async refresh() {
    const seq = ++this.issued;
    try {
      this.apply(seq, await this.api.request("GET", `${this.base}/state`));
    } catch (err) {
      if (!(err instanceof ApiError)) throw err;
      this.apply(seq, null, [404, 422].includes(err.status) ? "invalid" : "finished");
    }
  }

  poll(ms) {
    clearTimeout(this.pollTimer);
    this.pollTimer = setTimeout(() => this.refresh(), ms);
  }

  /** Render a state unless a newer request has already been rendered. */
  apply(seq, state, endKind = null) {
    if (seq < this.applied) return;
    this.applied = seq;
    clearTimeout(this.pollTimer);
    if (state === null) return this.show("end", `end:${endKind}`, () => views.renderEnd(endKind, null));
    this.state = state;
    window.__trustlab.state = state;
    window.__trustlab.renders += 1;
    $("study-title").textContent = state.study_title;
    $("progress").value = state.progress;
    this.render(state);
  }

  render(state) {
    const phase = state.phase;
    if (phase !== "practice" && phase !== "trial") this.trial.leave();
    if (TERMINAL.includes(phase)) clearInterval(this.heartbeat);
    if (!["practice", "trial", "debrief"].includes(phase)) this.poll(IDLE_POLL_MS);
    switch (phase) {
      case "consent": return this.show("consent", phase, () => views.renderConsent(state));
      case "instructions": return this.show("instructions", phase, () => views.renderInstructions(state));
      case "practice":
      case "trial":
        this.show("trial", "trial", () => {});
        return this.trial.render(state);
      case "questionnaire":
      case "shelf_survey":
        return this.show("survey", `survey:${views.surveyKey(state)}`, () => views.renderSurvey(state, this.lastNote(state)));
      case "debrief": return this.show("debrief", phase, () => views.renderDebrief(state));
      default: return this.show("end", `end:${phase}`, () => views.renderEnd(phase, state));
    }
  }

  /** On the shelf survey, what happened in the shelf's last trial (it was not shown yet). */
  lastNote(state) {
    const last = state.last_trial;
    if (state.phase !== "shelf_survey" || !last || last.practice || last.trial !== state.step.trial) return null;
    return `Last item: ${describeOutcome(last)[0]}`;
  }

  /** Show one section; build it only when the step on screen changes, then move focus to its heading. */
  show(section, viewKey, build) {
    const changed = viewKey !== this.viewKey;
    if (changed) {
      this.viewKey = viewKey;
      build();
      const title = $(`view-${section}`).querySelector("h1").textContent.trim();
      document.title = this.state ? `${title} – ${this.state.study_title}` : title;
    }
    if (section === this.section && !(changed && section !== "trial")) return;
    this.section = section;
    window.__trustlab.section = section;
    for (const name of SECTIONS) $(`view-${name}`).hidden = name !== section;
    const heading = $(`view-${section}`).querySelector("h1");
    if (heading) heading.focus();
  }

  // -- actions -------------------------------------------------------------------------
  /** One user action: a POST with its own Idempotency-Key (kept across retries), then render. */
  async act(path, body, { onConflict = "refresh", onRefused = null } = {}) {
    if (this.busy) return false;
    this.busy = true;
    const seq = ++this.issued;
    const error = this.errorElement();
    try {
      const state = await this.api.request("POST", `${this.base}/${path}`, { body, key: newKey() });
      if (error) error.textContent = "";
      this.apply(seq, state);
    } catch (err) {
      if (!(err instanceof ApiError)) throw err;
      this.events.log("action_refused", { path, status: err.status, detail: err.detail.slice(0, 200) });
      if (err.status === 422 && error) error.textContent = err.detail;
      if (err.status !== 422 || onConflict === "refresh") this.refresh();
    } finally {
      this.busy = false;
    }
    return true;
  }

  errorElement() {
    return { consent: $("consent-error"), instructions: $("instructions-error"), trial: $("trial-error"),
      survey: $("survey-error") }[this.section] || null;
  }

  async startTrial(ref) {
    const body = { practice: ref.practice, block: ref.block, trial: ref.trial };
    if (await this.act("trials/start", body)) return;
    this.trial.readyKey = null; // another action was under way: look again and start then
    this.poll(200);
  }

  submitSurvey() {
    const state = this.state;
    const { answers, missing } = views.collectAnswers(state);
    this.events.log("survey_submit", { questionnaire: state.questionnaire.id, missing: missing.length });
    if (missing.length) return;
    $("survey-submit").disabled = true;
    // The page's context too: a stale tab's answers then cannot land on another page of the same questionnaire.
    this.act("answers", { questionnaire: state.questionnaire.id, context: state.questionnaire.context, answers },
      { onConflict: "keep" })
      .finally(() => { $("survey-submit").disabled = false; });
  }
}

new App().start();
      if (onRefused) onRefused(err);
