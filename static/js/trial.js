// The trial screen: 3D view (same-origin viser iframe), the robot's messages, Intervene with a
// countdown, camera presets and teleoperation. Keys are captured in the capture phase on this
// window and on the iframe's window, so the viewer's own keyboard camera never sees them.

import { ApiError, newKey } from "./api.js";
import { N_, decimal, t as tr, tn } from "./i18n.js"; // (tr: t is a trial in this file)
import { Teleop } from "./teleop.js";
import { TeleopPanel } from "./teleop-panel.js";
import { ViewerPace } from "./viewerpace.js";

const $ = (id) => document.getElementById(id);
const OUTCOME_SHOW_MS = 1500; // the previous outcome stays on screen this long before the next trial
const NOTE_SHOW_MS = 6000; // ... or this long when it says more (a practice hint not followed)
const GET_READY_MS = 800;
const MOVE_KEYS = {
  KeyW: "x+", ArrowUp: "x+", KeyS: "x-", ArrowDown: "x-", KeyA: "y+", ArrowLeft: "y+",
  KeyD: "y-", ArrowRight: "y-", KeyR: "z+", KeyF: "z-", KeyQ: "j1+", KeyE: "j1-",
};
const CAMERA_KEYS = {
  Digit1: "world", Numpad1: "world", Digit2: "local", Numpad2: "local", Digit3: "end_effector", Numpad3: "end_effector",
};
// The 3D view may use at most this share of the page's main thread and draw this many frames a second
// (viewerpace.js). When its frames block the page for longer than VIEWER_SLOW_FRAME_MS (or it manages
// fewer than VIEWER_SLOW_FPS), this computer cannot draw it fast enough to steer by: the 2-D helper view
// then stands in for it during teleoperation, and the 3D view pauses behind it.
const VIEWER_BUDGET = 0.3;
const STEERING_MS = 400; // a key changed this recently counts as steering (a release or a new press may follow)
const VIEWER_MAX_FPS = 30;
const VIEWER_SLOW_FPS = 3; // (while the view draws freely: the budget allows more with cheap frames)
const VIEWER_SLOW_FRAME_MS = 120; // a frame blocking the page this long: too slow to steer by
const VIEWER_SLOW_WINDOWS = 2; // consecutive 2-s windows
// The decision window opens when the page proves the trial's scene on screen (POST trials/shown with the
// trial's scene_stamp). The 3D view: the server sends viser's client the node STAMP_PREFIX + stamp after the rest
// of the trial's first picture; once that node was in the client's scene before a render, the frame on screen was
// drawn from this trial's scene (ViewerPace.stampDrawn), whatever the previous trial left on screen. The 2-D
// helper view (where the 3D view could not load, or has not proven the scene SCENE_FALLBACK_MARGIN_MS before the
// server's bound): once it has drawn the scene fetched for this trial, which carries the same stamp. Without a
// proof the server opens the window anyway after timing.scene_wait_s, and the trial says so (wait_limit).
const SCENE_CHECK_MS = 100; // how often the page looks whether the scene is on screen
const SCENE_RETRY_MS = 300; // a report the server did not count (another trial's stamp) is looked at again this much later
const SCENE_FALLBACK_MARGIN_MS = 3000;
const STAMP_PREFIX = "/scene_stamp_"; // server/viewer/scene.py STAMP_PREFIX
const VIEW_CHECK_MS = 250; // during teleoperation: how often the page says whether its view is usable
// A 3D view that the 2-D view covered is shown again once it has drawn a new frame (checked this often), or after
// this long at most.
const FRESH_CHECK_MS = 50;
const FRESH_MAX_MS = 5000;
const HINT_NOT_FOLLOWED = { intervene: N_("trial.hint_not_followed.intervene"), rely: N_("trial.hint_not_followed.rely") };

export function trialKey(t) {
  return `${t.practice ? "practice" : `block${t.block}`}:${t.trial}`;
}

function signed(value) {
  const n = Math.abs(value);
  const sign = value > 0 ? "+" : value < 0 ? "−" : "";
  return `${sign}${Number.isInteger(n) ? n : n.toFixed(1)}`;
}

function points(value) {
  if (value === 0) return tr("units.no_points"); // as a person says it (was "±0 points")
  return tn("units.points_signed", Math.abs(value), { signed: signed(value) });
}

/** What happened in a finished trial, in words ([text, "success" | "failure" | "neutral"]). */
export function describeOutcome(last) {
  let text;
  let tone = "neutral";
  if (last.human_action === "intervene" || last.robot_action === "ask") {
    text = last.teleop_success === false ? tr("outcome.time_ran_out")
      : last.robot_action === "ask" ? tr("outcome.you_collected_for_robot") : tr("outcome.you_collected");
  } else if (last.outcome === "success") {
    [text, tone] = [tr("outcome.robot_collected"), "success"];
  } else {
    text = last.failure_mode === "collision" ? tr("outcome.robot_collided") : tr("outcome.robot_dropped");
    tone = "failure";
  }
  const score = last.practice ? tr("outcome.practice_no_points")
    : tr("outcome.score", { points: points(last.reward), score: signed(last.score).replace("+", "") });
  return [tr("outcome.sentence", { text, score }), tone];
}

/** A practice trial whose hint (rely / intervene) was not followed says so: the scored part differs. */
function hintNote(last) {
  if (!last.practice || last.hint_followed !== false) return "";
  const said = HINT_NOT_FOLLOWED[last.expected_human_action];
  return said ? tr("trial.hint_not_followed", { said: tr(said) }) : "";
}

export class TrialScreen {
  constructor(app) {
    this.app = app;
    this.active = false;
    this.key = null; // trial on screen
    this.readyKey = null;
    this.startTimer = null;
    this.pauseTicker = null; // the "Next item" pause (nextItemPause)
    this.viewTimer = null; // during teleoperation: tells the socket whether the view is usable
    this.freshTimer = null; // a resumed 3D view, invisible until it draws anew (viewReplaced)
    this.windowOpenedMs = null;
    this.deadline = null;
    this.ticker = null;
    this.intervening = false;
    this.camera = "world";
    this.padLoop = null;
    this.padButton = false;
    this.viewerPace = null;
    this.slowWindows = 0;
    this.presentingKey = null; // trial whose scene the page is bringing up (stage presenting)
    this.presentingStamp = null; // its scene's stamp (trial.scene_stamp)
    this.sceneFallbackAt = Infinity; // performance.now() when the 2-D view stands in for a 3D view still not showing it
    this.sceneFallback = false;
    this.sceneTimer = null;
    this.reporting = false;
    this.helperSceneKey = null; // trial whose scene the 2-D helper view shows before teleoperation
    this.helperSceneStamp = null; // and that scene's stamp
    this.helperSceneFetching = null;
    this.lateNotice = null; // "too_late" | "not_yet" while such a notice is on screen
    this.panel = new TeleopPanel(app);
    this.teleop = new Teleop({
      url: `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}${app.base}/teleop`,
      onSetup: (setup) => this.panel.setup(setup),
      onWorld: (world, guidance, events) => this.showWorld(world, guidance, events),
      onOver: (over) => this.teleopOver(over),
      onGone: () => app.poll(300),
      onConnection: (ok) => this.teleopConnection(ok),
      onError: (error) => this.panel.error(error),
      log: (kind, payload) => app.events.log(kind, payload),
    });
    this.panel.teleop = this.teleop;
    this.panel.onViewReplaced = (covered) => this.viewReplaced(covered);
    window.__trustlab.teleopPanel = this.panel;
    window.__trustlab.teleopClient = this.teleop; // what the socket says, for tests and debugging
    window.__trustlab.trialScreen = this;
    this.wire();
  }

  wire() {
    const onKey = (event) => this.onKey(event);
    window.addEventListener("keydown", onKey, true);
    window.addEventListener("keyup", onKey, true);
    this.onKeyHandler = onKey;
    $("intervene").disabled = false; // see setIntervene
    this.setIntervene(false);
    $("intervene").addEventListener("click", (event) => this.intervene(event.detail === 0 ? "keyboard" : "button"));
    for (const button of document.querySelectorAll(".camera button")) {
      button.addEventListener("click", () => this.setCamera(button.dataset.view, "button"));
    }
    for (const button of document.querySelectorAll(".pad button[data-action]")) this.wireHold(button);
    $("gripper-button").addEventListener("click", () => this.toggleGripper("button"));
    $("fine-toggle").addEventListener("change", (event) => {
      this.teleop.fineToggle = event.target.checked;
      this.app.events.log("fine_toggle", { on: event.target.checked });
    });
    window.addEventListener("blur", () => setTimeout(() => this.windowBlur(), 0));
    window.addEventListener("gamepadconnected", () => this.app.events.log("gamepad_connected"));
  }

  /** Press-and-hold with mouse, touch or pen; a keyboard click nudges for a moment. */
  wireHold(button) {
    const action = button.dataset.action;
    const source = `button:${action}`;
    const up = () => this.teleop.release(action, source);
    button.addEventListener("pointerdown", (event) => {
      if (!this.teleop.active) return;
      button.setPointerCapture(event.pointerId);
      this.teleop.press(action, source);
      this.app.events.log("button_down", { action });
    });
    for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) button.addEventListener(type, up);
    button.addEventListener("click", (event) => {
      if (event.detail !== 0 || !this.teleop.active) return;
      this.teleop.press(action, source);
      setTimeout(up, 250);
    });
  }

  // -- entering and leaving ------------------------------------------------------------
  enter() {
    if (this.active) return;
    this.active = true;
    this.restoreCamera();
    this.ensureViewer();
    this.padLoop = setInterval(() => this.pollGamepad(), 1000 / 30);
  }

  leave() {
    if (!this.active) return;
    this.active = false;
    clearInterval(this.padLoop);
    clearInterval(this.ticker);
    clearTimeout(this.startTimer);
    clearInterval(this.pauseTicker);
    this.stopViewWatch();
    this.stopPresenting();
    this.readyKey = null;
    this.teleop.stop();
    this.panel.show(false);
  }

  ensureViewer() {
    if ($("viewer-frame")) return;
    const frame = document.createElement("iframe");
    frame.id = "viewer-frame";
    frame.title = tr("trial.viewer_title");
    frame.setAttribute("allow", "gamepad");
    frame.addEventListener("load", () => this.viewerLoaded(frame));
    frame.src = `/viewer/${encodeURIComponent(this.app.token)}/`;
    $("viewer").prepend(frame);
  }

  viewerLoaded(frame) {
    let doc = null;
    try {
      doc = frame.contentDocument;
    } catch (_err) {
      doc = null; // an error page is cross-origin
    }
    const ok = doc !== null && doc.contentType === "text/html" && !/^chrome-error:/.test(doc.URL);
    frame.hidden = !ok;
    $("viewer-fallback").hidden = ok;
    this.app.events.log(ok ? "viewer_loaded" : "viewer_failed");
    window.__trustlab.viewer = ok ? "loaded" : "failed";
    this.panel.setHelperReason(ok ? null : "failed");
    if (!ok) return;
    if (sessionStorage.getItem(this.slowKey()) === "1") { // judged too slow before a reload: the 2-D view at once
      this.app.events.log("viewer_slow", { remembered: true });
      this.panel.setHelperReason("slow");
    }
    const win = frame.contentWindow;
    this.viewerPace = new ViewerPace(frame, {
      budget: VIEWER_BUDGET, maxFps: VIEWER_MAX_FPS, busy: () => this.teleop.steering(STEERING_MS),
      onRate: (fps, cost) => this.viewerRate(fps, cost),
    });
    window.__trustlab.viewerPace = this.viewerPace;
    win.addEventListener("keydown", this.onKeyHandler, true);
    win.addEventListener("keyup", this.onKeyHandler, true);
    win.addEventListener("blur", () => setTimeout(() => this.windowBlur(), 0));
  }

  /** A 3D view too slow to steer by (judged whenever it draws): the 2-D view stands in for it while steering. */
  viewerRate(fps, cost) {
    window.__trustlab.viewerRates = (window.__trustlab.viewerRates || 0) + 1;
    window.__trustlab.viewerFps = fps;
    window.__trustlab.viewerFrameMs = cost;
    const slow = (cost !== null && cost > VIEWER_SLOW_FRAME_MS) || fps < VIEWER_SLOW_FPS;
    this.slowWindows = slow ? this.slowWindows + 1 : 0;
    if (this.slowWindows >= VIEWER_SLOW_WINDOWS && this.panel.helperReason === null) {
      this.app.events.log("viewer_slow", { fps: Math.round(fps * 10) / 10, frame_ms: Math.round(cost || 0) });
      this.panel.setHelperReason("slow"); // from now on, the 2-D view stands in for it while steering
      try {
        sessionStorage.setItem(this.slowKey(), "1"); // (kept over a reload of this tab)
      } catch (_err) { /* storage off: the view is judged again after a reload */ }
    }
  }

  /** The 2-D view covers the 3D view (which pauses), or no longer does. A paused view still holds its last frame,
   * from before the 2-D view took over (the arm where it was then): it stays invisible until it has drawn anew. */
  viewReplaced(covered) {
    const pace = this.viewerPace;
    const frame = $("viewer-frame");
    if (!pace || !frame) return;
    const resuming = !covered && pace.paused;
    pace.setPaused(covered);
    clearInterval(this.freshTimer);
    frame.style.opacity = "";
    const renders = pace.renderCount();
    if (!resuming || renders === null) return;
    frame.style.opacity = "0"; // (still drawn: an invisible frame's view keeps rendering)
    const since = performance.now();
    this.freshTimer = setInterval(() => {
      const drawn = (pace.renderCount() ?? Infinity) > renders;
      if (!drawn && performance.now() - since < FRESH_MAX_MS) return;
      clearInterval(this.freshTimer);
      frame.style.opacity = "";
      if (!drawn) this.app.events.log("viewer_not_fresh", { waited_ms: FRESH_MAX_MS });
    }, FRESH_CHECK_MS);
  }

  stopViewWatch() {
    clearInterval(this.viewTimer);
    this.viewTimer = null;
  }

  slowKey() {
    return `trustlab.viewerSlow.${this.app.token}`;
  }

  /** Whether the participant can see the arm now: the 2-D view standing in (and drawn), or a 3D view that draws. */
  viewUsable() {
    const panel = this.panel;
    if (window.__trustlab.viewer === "failed" || panel.replacesView()) return panel.helper.drawnScene !== null;
    const pace = this.viewerPace;
    if (window.__trustlab.viewer !== "loaded" || !pace || pace.paused) return false;
    return (pace.renderCount() ?? 0) > 0 && pace.sampleFrame();
  }

  windowBlur() {
    const frame = $("viewer-frame");
    if (document.hasFocus() && document.activeElement === frame) {
      this.app.events.log("focus_viewer");
      return;
    }
    if (!document.hasFocus()) {
      this.teleop.releaseAll(); // key-ups are lost while another window has the focus
      this.app.events.log("window_blur");
    }
  }

  // -- rendering -----------------------------------------------------------------------
  render(state) {
    this.enter();
    this.showFacts(state);
    if (!state.trial || state.trial.stage !== "teleop") this.stopViewWatch();
    if (state.ready_to_start) return this.renderReady(state);
    clearTimeout(this.startTimer);
    clearInterval(this.pauseTicker);
    this.readyKey = null;
    const t = state.trial;
    const key = trialKey(t);
    if (key !== this.key) this.newTrial(t, key);
    $("robot-message").textContent = t.message;
    $("hint").hidden = !t.hint || t.stage === "teleop"; // while steering, the guidance says what to do
    $("hint").textContent = t.hint || "";
    if (t.stage === "presenting") return this.renderPresenting(t, key);
    this.stopPresenting();
    if (t.stage === "decision") return this.renderDecision(t, key);
    this.closeWindow();
    this.panel.showScene(null); // the 2-D view does not follow the robot's own attempt
    this.helperSceneKey = null;
    this.helperSceneStamp = null;
    if (t.stage === "attempt") return this.renderAttempt(t);
    if (t.stage === "teleop") return this.renderTeleop(t, key);
    this.teleop.stop();
    this.panel.show(false);
    this.app.poll(300);
  }

  showFacts(state) {
    const t = state.trial;
    $("score").textContent = String(state.score);
    if (!t) return; // between trials the previous trial's facts stay
    $("block-label").textContent = t.block_label;
    $("trial-count").textContent = tn("trial.count", t.n_trials, { trial: t.trial });
    $("shelf").textContent = String(t.shelf);
  }

  newTrial(t, key) {
    this.key = key;
    this.windowOpenedMs = null;
    this.intervening = false;
    $("outcome").textContent = "";
    $("outcome").className = "outcome";
    $("trial-error").textContent = "";
    this.lateNotice = null;
    this.app.events.log("trial_shown", { trial: key, stage: t.stage, robot_action: t.robot_action });
  }

  renderReady(state) {
    const ref = state.ready_to_start;
    const readyKey = JSON.stringify(ref);
    if (readyKey === this.readyKey) return;
    this.readyKey = readyKey;
    this.closeWindow();
    this.teleop.stop();
    this.panel.show(false);
    $("hint").hidden = true;
    const last = state.last_trial;
    const previous = last && (trialKey(last) === this.key
      || (last.practice === ref.practice && last.block === ref.block && last.trial === ref.trial - 1));
    let wait = GET_READY_MS;
    if (previous) {
      const [text, tone] = describeOutcome(last);
      $("outcome").textContent = text;
      $("outcome").className = `outcome ${tone}`;
      const note = hintNote(last); // in the hint's place: it is about the practice's instruction
      $("hint").hidden = !note;
      $("hint").textContent = note;
      wait = note ? NOTE_SHOW_MS : OUTCOME_SHOW_MS;
    } else {
      $("outcome").textContent = "";
    }
    $("robot-message").textContent = previous ? "" : tr("trial.moving_on");
    clearTimeout(this.startTimer);
    const pauseMs = previous ? 1000 * (state.timing.next_item_pause_s || 0) : 0;
    this.startTimer = setTimeout(() => {
      if (pauseMs > 0) this.nextItemPause(ref, pauseMs);
      else this.app.startTrial(ref);
    }, wait);
  }

  /** A visible pause between an outcome and the next item (timing.next_item_pause_s), so that a new decision
   * window never follows an outcome at once. */
  nextItemPause(ref, pauseMs) {
    const ends = performance.now() + pauseMs;
    $("robot-message").textContent = tr("trial.next_item");
    $("countdown").hidden = false;
    const tick = () => {
      const left = Math.max(0, ends - performance.now());
      $("countdown-bar").style.width = `${(100 * (pauseMs - left)) / pauseMs}%`;
      $("countdown-text").textContent = tr("trial.next_item_in", { seconds: Math.ceil(left / 1000) });
      if (left <= 0) {
        clearInterval(this.pauseTicker);
        this.app.startTrial(ref);
      }
    };
    clearInterval(this.pauseTicker);
    this.pauseTicker = setInterval(tick, 100);
    tick();
  }

  // -- before the decision window: the trial's scene comes up ---------------------------------
  renderPresenting(t, key) {
    this.panel.show(false);
    this.teleop.stop();
    this.closeWindow();
    $("robot-message").textContent = tr("trial.presenting");
    $("countdown").hidden = false;
    $("countdown-bar").style.width = "0%";
    $("countdown-text").textContent = tr("trial.countdown_waits");
    if (this.presentingKey !== key) {
      this.presentingKey = key;
      this.presentingStamp = t.scene_stamp;
      this.sceneFallback = false;
      this.sceneFallbackAt = performance.now() + (t.scene_wait_ms_left ?? 0) - SCENE_FALLBACK_MARGIN_MS;
      window.__trustlab.presenting = key;
    }
    this.ensureHelperScene(key);
    this.scheduleSceneCheck(SCENE_CHECK_MS);
    this.app.poll((t.scene_wait_ms_left ?? 1000) + 80); // the server opens the window by itself at its bound
  }

  stopPresenting() {
    clearTimeout(this.sceneTimer);
    this.sceneTimer = null;
    this.presentingKey = null;
    window.__trustlab.presenting = null;
  }

  scheduleSceneCheck(ms) {
    if (this.sceneTimer !== null || this.reporting || this.presentingKey === null) return;
    this.sceneTimer = setTimeout(() => {
      this.sceneTimer = null;
      this.checkScene();
    }, ms);
  }

  checkScene() {
    const t = this.app.state && this.app.state.trial;
    if (!this.active || !t || t.stage !== "presenting" || trialKey(t) !== this.presentingKey) return;
    if (!this.sceneFallback && window.__trustlab.viewer !== "failed" && performance.now() >= this.sceneFallbackAt) {
      this.sceneFallback = true; // the 3D view has not shown the scene in time: the 2-D view shows it instead
      this.app.events.log("scene_fallback_2d", { trial: this.presentingKey, viewer: window.__trustlab.viewer });
    }
    this.ensureHelperScene(this.presentingKey);
    const shown = this.sceneOnScreen();
    if (shown === null) this.scheduleSceneCheck(SCENE_CHECK_MS);
    else this.reportScene(t, shown);
  }

  /** {view: "3d" | "2d", at: performance.now() of the frame} once a frame drawn from the trial's scene is proven on
   * screen; null while it is not. */
  sceneOnScreen() {
    if (document.visibilityState !== "visible") return null; // a hidden tab shows nothing (and draws nothing)
    const stamp = this.presentingStamp;
    if (!stamp) return null;
    const viewer = window.__trustlab.viewer;
    if (viewer === "failed" || this.sceneFallback) {
      const helper = this.panel.helper;
      const drawn = this.helperSceneKey === this.presentingKey && this.helperSceneStamp === stamp
        && helper.scene !== null && helper.drawnScene === helper.scene;
      return drawn ? { view: "2d", at: helper.drawnAt } : null;
    }
    const pace = this.viewerPace;
    if (viewer !== "loaded" || !pace) return null;
    const at = pace.stampDrawn(STAMP_PREFIX + stamp);
    return at === null ? null : { view: "3d", at };
  }

  async reportScene(t, shown) {
    this.reporting = true;
    const key = this.presentingKey;
    if (window.__trustlab.sceneReported !== key) {
      window.__trustlab.sceneReported = key;
      this.app.events.log("scene_on_screen", { trial: key, view: shown.view, stamp: this.presentingStamp });
    }
    try {
      await this.app.act("trials/shown", { practice: t.practice, block: t.block, trial: t.trial, view: shown.view,
        scene_stamp: this.presentingStamp, client_time_ms: Math.max(0, shown.at) });
    } finally {
      this.reporting = false;
    }
    this.scheduleSceneCheck(SCENE_RETRY_MS); // still presenting (the answer was for another trial): look again
  }

  /** Where the 3D view could not load (or show the scene in time), the 2-D helper view shows the trial's scene
   * before teleoperation. */
  async ensureHelperScene(key) {
    const wanted = window.__trustlab.viewer === "failed" || (this.sceneFallback && this.presentingKey === key);
    if (!wanted || this.helperSceneKey === key || this.helperSceneFetching === key) return;
    this.helperSceneFetching = key;
    try {
      const shown = await this.app.api.request("GET", `${this.app.base}/trials/scene`);
      if (this.key !== key || !this.active) return;
      this.helperSceneKey = key;
      this.helperSceneStamp = shown.scene_stamp;
      this.panel.showScene(shown.scene, shown.world, window.__trustlab.viewer !== "failed");
    } catch (err) {
      if (!(err instanceof ApiError)) throw err;
      this.app.events.log("helper_scene_failed", { trial: key, status: err.status });
    } finally {
      this.helperSceneFetching = null;
    }
  }

  // -- the decision window ----------------------------------------------------------------
  renderDecision(t, key) {
    this.panel.show(false);
    this.teleop.stop();
    this.ensureHelperScene(key); // (after a reload during the window)
    if (this.windowOpenedMs === null) {
      this.windowOpenedMs = performance.now();
      this.windowTotal = (t.decision_window_s || t.decision_ms_left / 1000) * 1000;
      this.deadline = this.windowOpenedMs + t.decision_ms_left;
      this.app.events.log("decision_window_opened", {
        trial: this.key, decision_ms_left: t.decision_ms_left, decision_window_s: t.decision_window_s,
      });
      this.setIntervene(true);
      if (this.lateNotice === "not_yet") this.clearNotice();
      $("countdown").hidden = false;
      clearInterval(this.ticker);
      this.ticker = setInterval(() => this.tickCountdown(), 100);
      this.tickCountdown();
    }
    this.app.poll(Math.max(0, this.deadline - performance.now()) + 80);
  }

  tickCountdown() {
    const left = Math.max(0, this.deadline - performance.now());
    $("countdown-text").textContent = left > 0 ? tr("trial.seconds_left", { seconds: decimal(left / 1000, 1) })
      : tr("trial.time_up");
    $("countdown-bar").style.width = `${Math.min(100, (100 * left) / this.windowTotal)}%`;
    if (left === 0) {
      this.setIntervene(false);
      clearInterval(this.ticker);
    }
  }

  closeWindow() {
    clearInterval(this.ticker);
    this.setIntervene(false);
    $("countdown").hidden = true;
  }

  /**
   * Intervene looks and reads as unavailable outside the window (aria-disabled, not disabled): a press
   * still arrives, so that a press too late (or too early) is answered instead of silently ignored.
   */
  setIntervene(open) {
    $("intervene").setAttribute("aria-disabled", String(!open));
  }

  /** A press of Intervene outside the window: say why nothing happens (and log it). */
  notice(kind, source, detail = {}) {
    this.lateNotice = kind;
    $("trial-error").textContent = kind === "too_late" ? tr("trial.too_late") : tr("trial.not_yet");
    window.__trustlab.lateNotices = (window.__trustlab.lateNotices || 0) + 1;
    this.app.events.log(kind === "too_late" ? "intervene_too_late" : "intervene_too_early",
      { trial: this.key, source, ...detail });
  }

  clearNotice() {
    this.lateNotice = null;
    $("trial-error").textContent = "";
  }

  renderAttempt(t) {
    this.panel.show(false);
    this.teleop.stop();
    $("robot-message").textContent = tr("trial.robot_collecting");
    this.app.poll((t.attempt_ms_left || 0) + 80);
  }

  /** The teleoperation controls replace the Intervene button while the participant drives. */
  renderTeleop(t, key) {
    const fresh = this.teleop.wanted !== key;
    if (fresh) this.teleop.timeLeftMs = null; // the state's figure until the socket says
    this.panel.begin(t, fresh);
    if (t.robot_action === "auto") {
      $("robot-message").textContent = t.target ? tr("trial.you_take_over_target", { target: t.target })
        : tr("trial.you_take_over");
    }
    this.teleop.start(key);
    if (this.viewTimer === null) { // while the view is not usable (a reload, the view loading) the time limit waits
      const look = () => this.teleop.setViewUsable(this.viewUsable());
      this.viewTimer = setInterval(look, VIEW_CHECK_MS);
      look();
    }
    // The socket says when it is over; the state is looked at now and then for what the socket cannot say.
    this.app.poll(Math.min(2000, (t.teleop_ms_left ?? 2000) + 150));
  }

  showWorld(world, guidance, events) {
    this.panel.world(world, guidance, events);
    window.__trustlab.teleop = {
      world, guidance, scene: this.teleop.scene, seq: this.teleop.seq, ackSeq: this.teleop.ackSeq, events,
    };
  }

  teleopOver(over) {
    this.app.events.log("teleop_over", { reason: over.reason, retry: over.retry, recorded: over.trial_recorded });
    this.panel.over(over);
    this.app.refresh();
  }

  teleopConnection(ok) {
    this.panel.connection(ok);
    this.app.events.log(ok ? "teleop_connected" : "teleop_reconnecting");
  }

  // -- actions -------------------------------------------------------------------------
  async intervene(source) {
    const t = this.app.state && this.app.state.trial;
    if (!t || this.intervening) return;
    if (t.stage === "presenting") return this.notice("not_yet", source);
    const late = t.stage === "decision" && this.windowOpenedMs !== null && performance.now() > this.deadline;
    if (late || (t.stage === "attempt" && t.human_action === "rely")) {
      return this.notice("too_late", source, { known_by: "page", stage: t.stage });
    }
    if (t.stage !== "decision" || this.windowOpenedMs === null) return;
    const pressed = performance.now();
    this.intervening = true;
    this.setIntervene(false);
    this.app.events.log("intervene_pressed", { trial: this.key, source, since_window_ms: pressed - this.windowOpenedMs });
    const body = { practice: t.practice, block: t.block, trial: t.trial, window_opened_ms: this.windowOpenedMs,
      pressed_ms: pressed };
    // The server is the judge: a press that reaches it after the window closed is refused (409) and answered here.
    await this.app.act("trials/intervene", body, {
      onConflict: "refresh",
      onRefused: (err) => {
        this.intervening = false;
        if (err.status === 409 && err.body.message === "errors.window_closed") {
          this.notice("too_late", source, { known_by: "server", since_window_ms: pressed - this.windowOpenedMs });
        }
      },
    });
  }

  toggleGripper(source) {
    if (!this.teleop.active) return;
    const action = this.teleop.toggleGripper();
    this.app.events.log("gripper_toggle", { source, action });
  }

  /** Mark the chosen preset; the server keeps the session's view, the page remembers it per link. */
  showCamera(view) {
    this.camera = view;
    for (const button of document.querySelectorAll(".camera button")) {
      button.setAttribute("aria-pressed", String(button.dataset.view === view));
    }
    try {
      localStorage.setItem(`trustlab.camera.${this.app.token}`, view);
    } catch (_err) {
      // storage may be off; only the highlighted button is affected
    }
  }

  restoreCamera() {
    let view = null;
    try {
      view = localStorage.getItem(`trustlab.camera.${this.app.token}`);
    } catch (_err) {
      view = null;
    }
    if (view && document.querySelector(`.camera button[data-view="${CSS.escape(view)}"]`)) this.showCamera(view);
  }

  setCamera(view, source) {
    this.showCamera(view);
    this.app.events.log("camera", { view, source });
    const body = { view, client_time_ms: performance.now() };
    this.app.api.request("POST", `${this.app.base}/camera`, { body, key: newKey(), retry: false })
      .catch((err) => {
        if (!(err instanceof ApiError)) this.app.events.log("camera_failed", { view });
      });
  }

  // -- keyboard and gamepad --------------------------------------------------------------
  onKey(event) {
    if (!this.active || event.ctrlKey || event.metaKey || event.altKey) return;
    const down = event.type === "keydown";
    this.teleop.setFineKey(event.shiftKey && !(event.key === "Shift" && !down));
    const code = event.code;
    if (!(code in MOVE_KEYS || code in CAMERA_KEYS || code === "KeyG" || code === "Space")) return;
    if (code === "Space" && this.stage() !== "decision" && event.target instanceof Element
        && event.target.closest("button, input")) return; // Space activates the focused control

    event.preventDefault();
    event.stopImmediatePropagation();
    if (event.repeat) return;
    this.app.events.log(down ? "key_down" : "key_up", { code, stage: this.stage() });
    if (code in MOVE_KEYS) {
      if (!down) this.teleop.release(MOVE_KEYS[code], code);
      else if (this.teleop.active) this.teleop.press(MOVE_KEYS[code], code);
    } else if (down && code === "KeyG") {
      this.toggleGripper("key");
    } else if (down && code === "Space") {
      this.intervene("key");
    } else if (down) {
      this.setCamera(CAMERA_KEYS[code], "key");
    }
  }

  stage() {
    const s = this.app.state;
    return s && s.trial ? s.trial.stage : s && s.ready_to_start ? "between" : null;
  }

  pollGamepad() {
    const pads = navigator.getGamepads ? Array.from(navigator.getGamepads()).filter(Boolean) : [];
    if (pads.length === 0) return;
    const pad = pads[0];
    const a = (i) => pad.axes[i] || 0;
    const pressed = Boolean(pad.buttons[0] && pad.buttons[0].pressed);
    if (pressed && !this.padButton) {
      if (this.stage() === "decision") this.intervene("gamepad");
      else this.toggleGripper("gamepad");
    }
    this.padButton = pressed;
    // Left stick: forward/back and left/right; right stick: up/down and turning.
    if (this.teleop.active) this.teleop.setGamepad([-a(1), -a(0), -a(3)], -a(2));
  }
}
