// The participant page /p/{token}: always renders what GET /api/p/{token}/state says, polling
// while time passes and after each action. The server is the source of truth, so a reload,
// a reopened tab or a dropped connection simply resumes at the same step.

import { Api, ApiError, connectionNotice, errorText, newKey } from "./api.js";
import { EventLog, startHeartbeat } from "./events.js";
import { loadMessages, t } from "./i18n.js";
import { TrialScreen, describeOutcome } from "./trial.js";
import * as views from "./views.js";
import * as steps from "./steps.js";
import { WithdrawLink } from "./withdraw.js";

const $ = (id) => document.getElementById(id);
const IDLE_POLL_MS = 30000; // notices a withdrawal or an abandoned session on static pages
const DRAFT_DELAY_MS = 400; // a questionnaire's answers so far are saved this long after the last change
const BACK_NOTICE_MS = 15000;
const SECTIONS = ["loading", "consent", "instructions", "practice-done", "trial", "survey", "debrief", "end"];
const TERMINAL = ["debrief", "declined", "screened_out", "abandoned", "withdrawn"];
const ENDED_UNFINISHED = ["abandoned", "withdrawn"];

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
    this.draftTimer = null;
    this.draftSaving = null;
    this.noticeView = null;
    this.noticeTimer = null;
    this.explainedView = null; // the questionnaire page whose leaving was explained (or was this tab's own doing)
    window.__trustlab = { state: null, section: "loading", teleop: null, viewer: null, renders: 0 };
    window.__trustlab.events = this.events;
    this.withdraw = new WithdrawLink(this); // before the trial screen: its dialog's keys go first
    this.trial = new TrialScreen(this);
    this.wire();
  }

  wire() {
    $("consent-agree").addEventListener("click", () => this.act("consent", { agree: true }));
    $("consent-decline").addEventListener("click", () => {
      this.events.log("decline_asked");
      views.showDeclineConfirm(true);
    });
    $("decline-no").addEventListener("click", () => {
      this.events.log("decline_cancelled");
      views.showDeclineConfirm(false);
      $("consent-decline").focus();
    });
    $("decline-yes").addEventListener("click", () => this.act("consent", { agree: false }));
    $("notice-close").addEventListener("click", () => this.hideNotice());
    $("survey-form").addEventListener("change", () => this.scheduleDraft());
    $("survey-form").addEventListener("input", (event) => { // typing in a text answer
      if (event.target.tagName === "TEXTAREA") this.scheduleDraft();
    });
    $("instructions-done").addEventListener("click", () => this.act("instructions/done"));
    $("practice-done-continue").addEventListener("click", () => this.act("practice/done"));
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
    window.addEventListener("beforeunload", (event) => {
      if (!this.leavingLoses()) return;
      event.preventDefault();
      event.returnValue = ""; // the browser asks "Leave site?" (its own words; pages cannot set them)
    });
    this.wireBack();
  }

  /**
   * Back stays in the study: an extra history entry of this same page is pushed (on a user action, as
   * browsers skip entries pushed without one), and going back to it shows a notice instead. Pressing Back
   * again before the next click or key leaves; on the finished pages Back simply leaves.
   */
  wireBack() {
    this.backArmed = false;
    const arm = () => {
      if (this.backArmed || (this.state && TERMINAL.includes(this.state.phase)) || this.section === "end") return;
      history.pushState({ trustlabStay: true }, "", location.href);
      this.backArmed = true;
    };
    window.addEventListener("pointerdown", arm, true);
    window.addEventListener("keydown", arm, true);
    window.addEventListener("popstate", () => {
      if (!this.backArmed) return;
      this.backArmed = false;
      this.events.log("back_button", { phase: this.state ? this.state.phase : null });
      this.showNotice(t("notice.back"), { autoHideMs: BACK_NOTICE_MS });
    });
  }

  /** Whether closing or leaving the page now would lose something (a browser prompt asks first). */
  leavingLoses() {
    const state = this.state;
    if (this.draftTimer !== null || this.draftSaving) return true; // answers not yet saved as a draft
    // A running trial goes on without the page: its decision window would pass as if the robot was relied on.
    return Boolean(state && ["practice", "trial"].includes(state.phase) && state.trial && state.trial.stage !== "done");
  }

  // -- notices -----------------------------------------------------------------------------
  /** A message above the page; it stays through the next change of page (the page it explains), then goes. */
  showNotice(text, { autoHideMs = 0 } = {}) {
    $("notice-text").textContent = text;
    $("notice").hidden = false;
    this.noticeView = this.viewKey;
    clearTimeout(this.noticeTimer);
    if (autoHideMs) this.noticeTimer = setTimeout(() => this.hideNotice(), autoHideMs);
  }

  hideNotice() {
    $("notice").hidden = true;
    clearTimeout(this.noticeTimer);
  }

  /**
   * A questionnaire page with answers on it replaced by another page that this tab did not ask for: the session
   * moved on elsewhere (another tab or window answered the page; a withdrawn or abandoned session shows its own
   * end page instead). Say so rather than let the answers vanish without a word.
   */
  explainLeavingSurvey(section) {
    const leaving = this.viewKey;
    if (!leaving || !leaving.startsWith("survey:") || section === "end" || this.explainedView === leaving) return;
    if (!views.anythingAnswered()) return;
    this.explainedView = leaving;
    this.staleNotice({ body: { answered_elsewhere: true } });
  }

  /** A questionnaire page refused as out of date (409): say what became of its answers, truly for the case. */
  staleNotice(err) {
    this.showNotice(err.body && err.body.answered_elsewhere ? t("notice.stale_answered") : t("notice.stale_moved"));
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
      const state = await this.api.request("GET", `${this.base}/state`);
      await loadMessages(state.language); // (once: the session's language never changes)
      this.apply(seq, state);
    } catch (err) {
      if (!(err instanceof ApiError)) throw err;
      await loadMessages(navigator.language || "en"); // no session to say its language: the browser's
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
    if (state === null) {
      this.show("end", `end:${endKind}`, () => views.renderEnd(endKind, null));
      return this.withdraw.update(null);
    }
    this.state = state;
    window.__trustlab.state = state;
    window.__trustlab.renders += 1;
    $("study-title").textContent = state.study_title;
    $("preview-badge").hidden = !state.preview;
    $("progress").value = state.progress;
    this.render(state);
    this.withdraw.update(state);
  }

  render(state) {
    const phase = state.phase;
    if (phase !== "practice" && phase !== "trial") this.trial.leave();
    if (TERMINAL.includes(phase)) clearInterval(this.heartbeat);
    if (ENDED_UNFINISHED.includes(phase)) this.events.close(); // the server takes no more events from it (410)
    if (!["practice", "trial", "debrief"].includes(phase)) this.poll(IDLE_POLL_MS);
    switch (phase) {
      case "consent": return this.show("consent", phase, () => views.renderConsent(state));
      case "instructions": return this.show("instructions", phase, () => views.renderInstructions(state));
      case "practice_done": return this.show("practice-done", phase, () => steps.renderPracticeDone(state));
      case "practice":
      case "trial":
        this.show("trial", "trial", () => {});
        // The robot speaking is named as everywhere else: by the order the participant meets it ("Robot A").
        $("robot-heading").textContent = state.trial && !state.trial.practice ? state.trial.block_label
          : t("trial.robot");
        return this.trial.render(state);
      case "questionnaire":
      case "shelf_survey":
        return this.show("survey", `survey:${views.surveyKey(state)}`, () => views.renderSurvey(state, this.lastNote(state)));
      case "debrief": return this.show("debrief", phase, () => {
        views.renderDebrief(state);
        steps.renderFinalScore(state);
      });
      default: return this.show("end", `end:${phase}`, () => views.renderEnd(phase, state));
    }
  }

  /** On the shelf survey, what happened in the shelf's last trial (it was not shown yet). */
  lastNote(state) {
    const last = state.last_trial;
    if (state.phase !== "shelf_survey" || !last || last.practice || last.trial !== state.step.trial) return null;
    return t("survey.last_item", { outcome: describeOutcome(last)[0] });
  }

  /** Show one section; build it only when the step on screen changes, then move focus to its heading. */
  show(section, viewKey, build) {
    const changed = viewKey !== this.viewKey;
    if (changed) {
      this.explainLeavingSurvey(section);
      // A notice explains the move it came with: it stays on the page moved to and goes with the next move.
      if (!$("notice").hidden && this.noticeView !== this.viewKey) this.hideNotice();
      this.noticeView = this.viewKey;
      if (this.draftTimer !== null) clearTimeout(this.draftTimer);
      this.draftTimer = null;
      this.viewKey = viewKey;
      build();
      const title = $(`view-${section}`).querySelector("h1").textContent.trim();
      document.title = this.state ? `${title} – ${this.state.study_title}` : title;
    }
    if (section === this.section && !(changed && section !== "trial")) return;
    this.section = section;
    window.__trustlab.section = section;
    for (const name of SECTIONS) $(`view-${name}`).hidden = name !== section;
    // Progress means nothing on an end page (declined, withdrawn, an invalid link) or before the state is known.
    document.querySelector(".topbar").classList.toggle("no-progress", section === "end" || section === "loading");
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
      await loadMessages(state.language);
      if (error) error.textContent = "";
      this.apply(seq, state);
    } catch (err) {
      if (!(err instanceof ApiError)) throw err;
      this.events.log("action_refused", { path, status: err.status, detail: err.detail.slice(0, 200) });
      if (onRefused) onRefused(err);
      if (err.status === 422 && error) error.textContent = errorText(err);
      if (err.status !== 422 || onConflict === "refresh") this.refresh();
    } finally {
      this.busy = false;
    }
    return true;
  }

  errorElement() {
    return { consent: $("consent-error"), instructions: $("instructions-error"), trial: $("trial-error"),
      survey: $("survey-error"), "practice-done": $("practice-done-error") }[this.section] || null;
  }

  async startTrial(ref) {
    const body = { practice: ref.practice, block: ref.block, trial: ref.trial };
    if (await this.act("trials/start", body)) return;
    this.trial.readyKey = null; // another action was under way: look again and start then
    this.poll(200);
  }

  async submitSurvey() {
    const state = this.state;
    const { answers, missing } = views.collectAnswers(state);
    this.events.log("survey_submit", { questionnaire: state.questionnaire.id, missing: missing.length });
    if (missing.length) return;
    $("survey-submit").disabled = true;
    this.explainedView = this.viewKey; // this tab moves on by itself (or says why not: staleNotice)
    clearTimeout(this.draftTimer); // the answers themselves go now; a draft still on its way goes first
    this.draftTimer = null;
    if (this.draftSaving) await this.draftSaving;
    // The page's context too: a stale tab's answers then cannot land on another page of the same questionnaire.
    this.act("answers", { questionnaire: state.questionnaire.id, context: state.questionnaire.context, answers },
      { onConflict: "keep", onRefused: (err) => { if (err.status === 409) this.staleNotice(err); } })
      .finally(() => { $("survey-submit").disabled = false; });
  }

  /** Save the page's answers so far a moment after the last change (a reload then restores them). */
  scheduleDraft() {
    clearTimeout(this.draftTimer);
    this.draftTimer = setTimeout(() => {
      this.draftTimer = null;
      this.draftSaving = this.saveDraft().finally(() => { this.draftSaving = null; });
    }, DRAFT_DELAY_MS);
  }

  async saveDraft() {
    const state = this.state;
    if (!state || !state.questionnaire) return;
    const q = state.questionnaire;
    const body = { questionnaire: q.id, context: q.context, answers: views.answersSoFar(state) };
    try {
      await this.api.request("PUT", `${this.base}/answers/draft`, { body });
    } catch (err) {
      if (!(err instanceof ApiError)) throw err;
      this.events.log("draft_refused", { status: err.status, detail: err.detail.slice(0, 200) });
      if (this.state !== state) return; // the page has moved on meanwhile (and said why: explainLeavingSurvey)
      if (err.status === 409) {
        this.explainedView = this.viewKey;
        this.staleNotice(err);
      }
      if (err.status !== 422) this.refresh();
    }
  }
}

new App().start();
