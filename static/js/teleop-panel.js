// The teleoperation panel: what to collect, the time left, the server's guidance (next step, "close
// enough", "over the bin", "blocked") with a step checklist, the guided-practice banner, and the 2-D
// helper view. Everything shown comes from the socket's hello and world messages (server/teleop_messages.py).

import { Helper2D } from "./fallback2d.js";
import { N_, t } from "./i18n.js";
import { duration, teleopTimeLimit } from "./views.js";

const $ = (id) => document.getElementById(id);
/** The checklist, in the order a successful teleoperation passes the guidance steps. */
const STEPS = ["move_above_item", "lower", "close_gripper", "lift", "turn_to_bin", "move_over_bin", "release"];
/** Guidance steps outside the checklist, shown as this checklist position. */
const STEP_AT = { open_gripper: 0, wait_for_item: 0, done: STEPS.length };
const BLOCKED_SHOW_MS = 2000; // a refused move is reported this long (one world message says it)
const ERROR_SHOW_MS = 4000;
const URGENT_MS = 10000; // the time left turns red below this
/** Each motion action: its key (static/js/trial.js MOVE_KEYS), which way it moves, and the action that undoes it. */
const MOVES = {
  "x+": ["W", N_("teleop.move.towards_shelf"), "x-"], "x-": ["S", N_("teleop.move.away_from_shelf"), "x+"],
  "y+": ["A", N_("teleop.move.left"), "y-"], "y-": ["D", N_("teleop.move.right"), "y+"],
  "z+": ["R", N_("teleop.move.up"), "z-"], "z-": ["F", N_("teleop.move.down"), "z+"],
  "j1+": ["Q", N_("teleop.move.turning_left"), "j1-"], "j1-": ["E", N_("teleop.move.turning_right"), "j1+"],
};
const ITEM_TEXT = {
  on_shelf: N_("teleop.item.on_shelf"), grasped: N_("teleop.item.grasped"), in_bin: N_("teleop.item.in_bin"),
  dropped: N_("teleop.item.dropped"),
};
const GRIPPER_TEXT = {
  closing: N_("teleop.gripper.closing"), opening: N_("teleop.gripper.opening"), closed: N_("teleop.gripper.closed"),
  open: N_("teleop.gripper.open"),
};

function clock(ms) {
  const s = Math.ceil(ms / 1000);
  return s >= 120 ? `${Math.floor(s / 60)}:${String(s % 60).padStart(2, "0")}` : t("units.seconds_short", { seconds: s });
}

/** Words joined with the language's "and": "W and A". */
function both(words) {
  return new Intl.ListFormat(document.documentElement.lang || "en", { type: "conjunction" }).format(words);
}

export class TeleopPanel {
  constructor(app) {
    this.app = app;
    this.helper = new Helper2D($("helper2d-canvas"));
    this.helperWanted = this.loadHelperChoice();
    this.helperReason = null; // "failed" (no 3D view) | "slow" (the 3D view cannot keep up) | null
    this.shown = false;
    this.tutorial = null;
    this.limitS = null;
    this.blockedUntil = 0;
    this.errorTimer = null;
    this.ticker = null;
    this.teleop = null; // set by the trial screen
    this.slowOptOut = false; // the participant asked for the slow 3D view back
    this.sceneOnly = false; // before teleoperation, without a 3D view: the helper shows the trial's scene
    this.sceneCover = false; // ... over a 3D view that has not shown it in time
    this.onViewReplaced = () => {}; // (covered) the 3D view is hidden behind the helper: it may pause
    $("helper2d-toggle").checked = this.helperWanted;
    $("helper2d-toggle").addEventListener("change", (event) => this.toggleHelper(event.target.checked));
  }

  /** The panel for a teleoperated trial (from the state); the socket's hello fills in the rest. */
  begin(trial, fresh) {
    this.show(true);
    if (fresh) {
      this.resetGuide();
      $("guide-text").textContent = t("teleop.connecting");
      $("teleop-status").textContent = "";
    }
    // The socket's hello is the more recent word on the guided try; the state stands in until it came.
    this.setTutorial((this.teleop.setup ? this.teleop.setup.tutorial : trial.tutorial) || null);
    if (!this.teleop.setup) this.limitS = teleopTimeLimit(this.app.state);
    if (this.teleop.timeLeftMs === null && trial.teleop_ms_left !== null && trial.teleop_ms_left !== undefined) {
      this.teleop.setTimeLeft(trial.teleop_ms_left);
    }
    this.tick();
  }

  show(on) {
    if (on === this.shown) return;
    this.shown = on;
    this.sceneOnly = false;
    $("teleop-panel").hidden = !on;
    $("decision").hidden = on;
    clearInterval(this.ticker);
    if (on) this.ticker = setInterval(() => this.tick(), 250);
    else {
      this.setTutorial(null);
      this.helper.setScene(null); // the next teleoperation's hello brings its own
    }
    this.layoutHelper();
  }

  setup(setup) {
    this.limitS = setup.time_limit_s;
    this.setTutorial(setup.tutorial || null);
    this.helper.setScene(setup.scene);
    this.layoutHelper();
    this.tick();
  }

  /**
   * Before teleoperation (the window to intervene), where the 3D view could not load: the helper shows the
   * trial's scene with the robot parked at the shelf (GET trials/scene): the item, obstacles and bin it works with.
   * null hides it again (the helper does not follow the robot's own attempt). cover: over a 3D view that loaded
   * but has not shown the scene in time.
   */
  showScene(scene, world, cover = false) {
    if (this.shown) return;
    this.sceneOnly = scene !== null;
    this.sceneCover = this.sceneOnly && cover;
    this.helper.setScene(scene);
    this.helper.world = world;
    this.helper.guidance = null;
    this.layoutHelper();
  }

  setTutorial(tutorial) {
    this.tutorial = tutorial;
    $("teleop-panel").classList.toggle("tutorial", Boolean(tutorial));
    $("tutorial-banner").hidden = !tutorial;
    $("tutorial-keys").hidden = !tutorial;
    if (tutorial) {
      $("tutorial-banner").textContent = t("teleop.tutorial_banner", { try: tutorial.try_number, tries: tutorial.max_tries });
    }
  }

  resetGuide() {
    this.blockedUntil = 0;
    for (const id of ["guide-grasp", "guide-bin", "guide-blocked"]) $(id).hidden = true;
    this.markSteps(0);
  }

  world(world, guidance, events) {
    if (guidance) this.showGuidance(guidance, events);
    this.showStatus(world, events);
    if (this.helperOn()) this.helper.update(world, guidance);
    else this.helper.world = world; // drawn when it is switched on
    this.helper.guidance = guidance;
  }

  showGuidance(guidance, events) {
    const text = $("guide-text");
    if (text.textContent !== guidance.text) text.textContent = guidance.text;
    $("guide-grasp").hidden = !guidance.can_grasp;
    $("guide-bin").hidden = !guidance.over_bin;
    if (guidance.blocked || events.includes("blocked")) {
      const advice = this.blockedAdvice();
      if ($("guide-blocked").textContent !== advice) $("guide-blocked").textContent = advice;
      this.blockedUntil = performance.now() + BLOCKED_SHOW_MS;
    }
    $("guide-blocked").hidden = performance.now() >= this.blockedUntil;
    this.markSteps(STEP_AT[guidance.step] ?? STEPS.indexOf(guidance.step));
  }

  /**
   * What to do when a move is refused: let go of the key that pushes into the obstacle and move the other way
   * (from what is held now: keys or on-screen buttons); up and over it when the push was sideways or down.
   */
  blockedAdvice(held = this.teleop ? [...this.teleop.held.keys()] : []) {
    const moves = held.filter((action) => action in MOVES);
    if (moves.length === 0) {
      return this.teleop && this.teleop.gamepad && (this.teleop.gamepad.ee.some((v) => v) || this.teleop.gamepad.joint)
        ? t("teleop.blocked_stick") : t("teleop.blocked");
    }
    const keys = moves.map((action) => MOVES[action][0]);
    const back = moves.map((action) => MOVES[action][2]).filter((action) => !moves.includes(action));
    const undo = both(back.map((action) => t("teleop.key_way", { key: MOVES[action][0], way: t(MOVES[action][1]) })));
    const params = { moving: both(moves.map((action) => t(MOVES[action][1]))), keys: both(keys), undo };
    return moves.includes("z+") || moves.includes("z-") ? t("teleop.blocked_moving", params)
      : t("teleop.blocked_moving_or_over", params);
  }

  markSteps(current) {
    $("guide-steps").querySelectorAll("li").forEach((li, i) => {
      li.classList.toggle("done", i < current);
      li.classList.toggle("current", i === current);
      if (i === current) li.setAttribute("aria-current", "step");
      else li.removeAttribute("aria-current");
    });
  }

  showStatus(world, events) {
    const closed = !this.teleop.gripperOpen();
    const moving = Math.abs(world.gripper - world.gripper_target) > 1e-3;
    const gripper = moving ? (closed ? "closing" : "opening") : closed ? "closed" : "open";
    const item = ITEM_TEXT[world.item.mode] ? t(ITEM_TEXT[world.item.mode]) : world.item.mode;
    const status = t("teleop.status", { gripper: t(GRIPPER_TEXT[gripper]), item });
    const note = events.includes("grasped") ? t("teleop.got_it") : events.includes("dropped") ? t("teleop.fell") : "";
    $("teleop-status").textContent = note ? `${status} ${note}` : status;
  }

  over(over) {
    const key = {
      deposited: N_("teleop.over.deposited"),
      time_limit: over.retry ? N_("teleop.over.retry") : N_("teleop.over.time_limit"),
      ended: N_("teleop.over.ended"),
    }[over.reason];
    $("guide-text").textContent = key ? t(key) : "";
    $("guide-grasp").hidden = true;
    $("guide-bin").hidden = true;
    if (over.reason === "deposited") this.markSteps(STEPS.length);
    if (over.retry) this.resetGuide();
    this.tick();
  }

  error(message) {
    $("trial-error").textContent = t("teleop.refused");
    this.app.events.log("teleop_refused", { reason: String(message).slice(0, 200) });
    clearTimeout(this.errorTimer);
    this.errorTimer = setTimeout(() => { $("trial-error").textContent = ""; }, ERROR_SHOW_MS);
  }

  connection(ok) {
    if (!ok) $("teleop-status").textContent = t("connection.lost");
  }

  tick() {
    const left = this.teleop.timeLeftNow();
    const time = $("teleop-time");
    if (!this.shown || left === null) {
      time.textContent = this.limitS ? t("teleop.time_limit", { duration: duration(this.limitS) }) : "";
      return;
    }
    if (this.tutorial) {
      time.textContent = t("teleop.time_left_tutorial", { time: clock(left) });
      time.classList.remove("urgent");
    } else {
      time.textContent = t("teleop.time_left", { time: clock(left) });
      time.title = this.limitS ? t("teleop.time_limit", { duration: duration(this.limitS) }) : "";
      time.classList.toggle("urgent", left < URGENT_MS);
    }
    if (this.blockedUntil && performance.now() >= this.blockedUntil) $("guide-blocked").hidden = true;
  }

  // -- the 2-D helper view ---------------------------------------------------------------------
  /**
   * Why the helper must be shown: "failed" (no 3D view) or "slow" (this computer cannot draw the 3D view
   * fast enough to steer by); null: only if the participant switched it on. Either way it fills the
   * viewer while the participant steers; a slow 3D view is paused behind it unless the participant
   * asks for it back (unticks the toggle).
   */
  setHelperReason(reason) {
    if (reason === this.helperReason) return;
    this.helperReason = reason;
    this.layoutHelper();
  }

  helperOn() {
    if (this.helper.scene === null) return false;
    return this.shown ? this.replacesView() || this.helperWanted
      : this.sceneOnly && (this.helperReason === "failed" || this.sceneCover);
  }

  /** The helper stands in for the 3D view (fills the viewer). */
  replacesView() {
    return this.helperReason === "failed" || (this.helperReason === "slow" && !this.slowOptOut);
  }

  toggleHelper(on) {
    if (this.helperReason === "slow") this.slowOptOut = !on;
    else {
      this.helperWanted = on;
      this.saveHelperChoice();
    }
    this.app.events.log("helper2d", { on, source: "toggle", reason: this.helperReason });
    this.layoutHelper();
  }

  layoutHelper() {
    const on = this.helperOn();
    const covering = on && !this.shown && this.sceneCover;
    const full = on && (this.replacesView() || covering);
    $("helper2d").hidden = !on;
    $("helper2d").classList.toggle("full", full);
    $("helper2d-toggle").checked = on || (!this.shown && this.helperWanted);
    $("helper2d-toggle").disabled = this.helperReason === "failed";
    const note = covering ? t("helper2d.covering")
      : full && this.helperReason === "slow" ? t("helper2d.slow") : "";
    $("helper2d-note").hidden = !note;
    $("helper2d-note").textContent = note;
    this.onViewReplaced(full && this.helperReason === "slow");
    if (on) this.helper.request();
  }

  loadHelperChoice() {
    try {
      return localStorage.getItem(`trustlab.helper2d.${this.app.token}`) === "on";
    } catch (_err) {
      return false; // storage off: the choice lasts as long as the page
    }
  }

  saveHelperChoice() {
    try {
      localStorage.setItem(`trustlab.helper2d.${this.app.token}`, this.helperWanted ? "on" : "off");
    } catch (_err) {
      // storage off: see loadHelperChoice
    }
  }
}
