// Teleoperation client for the socket /api/p/{token}/teleop (protocol 2, server/teleop_messages.py;
// JSON Schema at /api/schema/teleop.json). The page sends its *input state* — what is held now —
// only when it changes, plus a keepalive every limits.keepalive_s while a motion is held. The server
// moves the arm on its own clock, so a page starved by a slow 3D view does not slow the arm; it
// pushes `world` messages (world, guidance, events, time left) and says `over` at the end.

/**
 * The speeds the page asks for while a key, an on-screen button or a full gamepad stick is held.
 * The server clamps them to hello.teleop.limits (max_ee_speed, max_joint_speed).
 *   ee:    gripper velocity along each world axis (W/S x, A/D y, R/F z), m/s
 *   joint: rate of joint 1, the arm's turn about the mast (Q/E), rad/s
 * The *Fine values apply with Shift held or the "Slow, precise moves" toggle on.
 */
export const SPEEDS = Object.freeze({ ee: 0.2, eeFine: 0.025, joint: 0.6, jointFine: 0.1 });

const GRIPPER_OPEN = 0.1; // m: gripper_target when fully open (WorldView.gripper_target)
const DEADZONE = 0.15; // gamepad sticks
const STICK_STEP = 0.1; // stick deflection is rounded to this: a trembling stick is not a stream of changes
const BURST = 4; // messages the page may send at once before pacing itself to limits.rate_limit_hz
const RETRY_AFTER_OVER_MS = 200; // a guided try that ran out of time: reconnect for the next try
const CLOSE_SESSION_GONE = 4404;
// Refusals that need no message: the teleoperation ended under us (another tab, the time limit).
const BENIGN_ERRORS = /^not teleoperating/;
const RATE_LIMITED = /^too many messages/; // the server's rate limit refused a message: the page sends it again
const RESEND_AFTER_MS = 100;

/** Motion actions: world-frame axis (x towards the shelf, y to the left, z up) or joint 1. */
export const ACTIONS = {
  "x+": ["ee", 0, 1], "x-": ["ee", 0, -1],
  "y+": ["ee", 1, 1], "y-": ["ee", 1, -1],
  "z+": ["ee", 2, 1], "z-": ["ee", 2, -1],
  "j1+": ["joint", 0, 1], "j1-": ["joint", 0, -1],
};

const round3 = (v) => Math.round(v * 1000) / 1000;

export class Teleop {
  /**
   * Callbacks: onSetup(setup) after each hello with a teleoperation; onWorld(world, guidance, events);
   * onOver(over) when the server says the teleoperation ended (over.retry: a new guided try follows);
   * onGone() when the socket says there is nothing to teleoperate (the app looks at its state again);
   * onConnection(ok); onError(text) for a refused message; log(kind, payload) for the event log.
   */
  constructor({ url, onSetup, onWorld, onOver, onGone, onConnection, onError, log }) {
    Object.assign(this, { url, onSetup, onWorld, onOver, onGone, onConnection, onError, log });
    this.held = new Map(); // action -> Set of sources (key codes, button ids)
    this.fineKey = false;
    this._fineToggle = false;
    this.gamepad = { ee: [0, 0, 0], joint: 0 };
    this.ws = null;
    this.wanted = null; // trial key string while teleoperation is wanted
    this.seq = 0; // last seq sent (input or keepalive)
    this.inputSeq = -1; // seq of the last input message sent
    this.ackSeq = -1;
    this.lastAck = null;
    this.lastSent = null; // {type, seq, client_ms} of the last message sent
    this.sentMotion = null; // JSON of the motion the server holds (as far as the page knows)
    this.gripperPending = null; // "open" | "close" waiting to be sent
    this.lastInputGripper = null; // the gripper action of the last input sent (sent again if it is refused)
    this.setup = null; // hello.teleop
    this.hellos = 0; // hellos with a teleoperation received (a new guided try is a new hello)
    this.world = null;
    this.guidance = null;
    this.lastWorldMessage = null;
    this.over = null;
    this.timeLeftMs = null;
    this.timeLeftAt = 0; // performance.now() when timeLeftMs was received
    this.tokens = BURST;
    this.tokensAt = 0;
    this.lastInputAt = -Infinity; // performance.now() of the last change of what is held
    this.retryMs = 500;
    this.timer = null; // reconnect
    this.keepaliveTimer = null;
    this.paceTimer = null;
  }

  get active() {
    return this.wanted !== null;
  }

  get open() {
    return this.ws !== null && this.ws.readyState === WebSocket.OPEN;
  }

  /** The socket is open and the server has said what it teleoperates. */
  get ready() {
    return this.open && this.setup !== null;
  }

  get scene() {
    return this.setup && this.setup.scene;
  }

  get limits() {
    return this.setup && this.setup.limits;
  }

  /** Time left (ms) now, counted down locally from the server's latest figure. */
  timeLeftNow() {
    if (this.timeLeftMs === null) return null;
    return Math.max(0, this.timeLeftMs - (performance.now() - this.timeLeftAt));
  }

  /** Teleoperate the trial `key` (a no-op when already doing so). */
  start(key) {
    if (this.wanted === key) return;
    this.stop();
    this.wanted = key;
    this.connect();
  }

  stop() {
    this.wanted = null;
    clearTimeout(this.timer);
    this.closeSocket();
    this.releaseAll(false);
    this.gripperPending = null;
  }

  closeSocket() {
    clearTimeout(this.keepaliveTimer);
    clearTimeout(this.paceTimer);
    if (!this.ws) return;
    const ws = this.ws;
    this.ws = null;
    ws.onclose = null;
    ws.onmessage = null;
    ws.close(1000, "trial over");
  }

  connect() {
    const ws = new WebSocket(this.url);
    this.ws = ws;
    this.setup = null;
    this.over = null;
    this.sentMotion = null;
    this.gripperPending = null; // a G pressed while disconnected is not replayed later
    ws.onopen = () => {
      this.retryMs = 500;
      this.onConnection(true);
    };
    ws.onmessage = (event) => this.receive(JSON.parse(event.data));
    ws.onclose = (event) => this.closed(ws, event);
  }

  closed(ws, event) {
    if (this.ws !== ws) return;
    this.ws = null;
    clearTimeout(this.keepaliveTimer);
    clearTimeout(this.paceTimer);
    if (event.code === CLOSE_SESSION_GONE) {
      this.wanted = null;
      this.onGone();
      return;
    }
    const over = this.over;
    if (over && over.retry && this.wanted !== null) {
      this.timer = setTimeout(() => this.wanted !== null && this.connect(), RETRY_AFTER_OVER_MS);
      return;
    }
    if (over || this.wanted === null) return;
    this.onConnection(false);
    this.log("teleop_disconnected", { code: event.code });
    this.timer = setTimeout(() => this.wanted !== null && this.connect(), this.retryMs);
    this.retryMs = Math.min(this.retryMs * 2, 8000);
  }

  receive(message) {
    switch (message.type) {
      case "hello": return this.hello(message);
      case "ack": return this.ack(message);
      case "world": return this.worldMessage(message);
      case "over": return this.overMessage(message);
      default: return undefined;
    }
  }

  hello(message) {
    if (!message.teleop) { // not teleoperated (any more, or not yet): the app looks at its state again
      this.stop();
      this.onGone();
      return;
    }
    this.setup = message.teleop;
    this.hellos += 1;
    this.setTimeLeft(message.teleop.time_left_ms);
    this.world = message.teleop.world;
    this.guidance = message.teleop.guidance;
    this.onSetup(this.setup);
    this.onWorld(this.world, this.guidance, []);
    this.viewSent = null; // a new socket: the server knows nothing of the view yet
    this.sendView();
    if (this.moving()) this.update(true); // keys held through a reconnect keep moving the arm
  }

  /**
   * Whether the participant can see the arm now (the page's 3D view drawing, or the 2-D view). While it cannot
   * (a reload in the middle of a teleoperation, the view still loading), the server's time limit waits, within
   * limits.max_view_wait_s (view messages).
   */
  setViewUsable(usable) {
    if (this.viewUsable === usable) return;
    this.viewUsable = usable;
    this.sendView();
  }

  /** Say "no usable view" on each socket while that is so, and "usable" once it is again (nothing otherwise). */
  sendView() {
    if (!this.ready || !this.setup || this.viewUsable === undefined || this.viewUsable === null) return;
    if (this.viewUsable === this.viewSent || (this.viewUsable && this.viewSent !== false)) return;
    this.send({ type: "view", seq: this.seq + 1, client_ms: performance.now(), usable: this.viewUsable });
    this.viewSent = this.viewUsable;
  }

  ack(message) {
    this.ackSeq = Math.max(this.ackSeq, message.seq ?? -1);
    this.lastAck = { seq: message.seq, ok: message.ok, error: message.error || null };
    if (message.ok) return;
    if (RATE_LIMITED.test(message.error || "")) {
      // A burst (e.g. a page that stalled and then flushed its keys) went past the server's limit. If the refused
      // message was the last input, the arm is not doing what the keys say: send the held state again shortly.
      if (message.seq === this.inputSeq) {
        if (this.lastInputGripper !== null && this.gripperPending === null) this.gripperPending = this.lastInputGripper;
        this.sentMotion = null;
        clearTimeout(this.resendTimer);
        this.resendTimer = setTimeout(() => this.update(), RESEND_AFTER_MS);
      }
      return;
    }
    if (!BENIGN_ERRORS.test(message.error || "")) this.onError(message.error || "refused");
  }

  worldMessage(message) {
    this.lastWorldMessage = message;
    this.world = message.world;
    this.guidance = message.guidance;
    this.setTimeLeft(message.time_left_ms);
    this.onWorld(message.world, message.guidance, message.events || []);
  }

  overMessage(message) {
    this.over = message;
    clearTimeout(this.keepaliveTimer);
    if (!message.retry) {
      this.wanted = null;
      this.releaseAll(false);
    }
    this.onOver(message);
  }

  setTimeLeft(ms) {
    if (ms === undefined || ms === null) return;
    this.timeLeftMs = ms;
    this.timeLeftAt = performance.now();
  }

  // -- input ------------------------------------------------------------------------
  press(action, source) {
    const sources = this.held.get(action) || new Set();
    sources.add(source);
    this.held.set(action, sources);
    this.update();
  }

  release(action, source) {
    const sources = this.held.get(action);
    if (!sources) return;
    sources.delete(source);
    if (sources.size === 0) this.held.delete(action);
    this.update();
  }

  /** Let go of everything (window blur, end of a trial); `send` tells the server the arm should stop. */
  releaseAll(send = true) {
    this.held.clear();
    this.fineKey = false;
    this.gamepad = { ee: [0, 0, 0], joint: 0 };
    if (send) this.update();
  }

  setFineKey(on) {
    if (on === this.fineKey) return;
    this.fineKey = on;
    this.update();
  }

  set fineToggle(on) {
    this._fineToggle = on;
    this.update();
  }

  get fineToggle() {
    return this._fineToggle;
  }

  get fine() {
    return this.fineKey !== this._fineToggle; // Shift inverts the on-screen "precise" toggle
  }

  /** "G": open when closed (or holding the item), close when open, judged from the latest world. */
  toggleGripper() {
    this.gripperPending = this.gripperOpen() ? "close" : "open";
    this.update();
    return this.gripperPending;
  }

  gripperOpen() {
    return this.world === null || this.world.gripper_target >= GRIPPER_OPEN - 1e-6;
  }

  setGamepad(ee, joint) {
    const shape = (v) => (Math.abs(v) < DEADZONE ? 0 : Math.round(v / STICK_STEP) * STICK_STEP);
    this.gamepad = { ee: ee.map(shape), joint: shape(joint) };
    this.update();
  }

  /** A motion is held, or the input changed within the last `ms`. */
  steering(ms) {
    return this.active && (this.moving() || performance.now() - this.lastInputAt < ms);
  }

  moving() {
    return this.held.size > 0 || this.gamepad.ee.some((v) => v !== 0) || this.gamepad.joint !== 0;
  }

  /** What is held now as the input message's motion fields (empty when nothing is held). */
  motion() {
    const ee = [...this.gamepad.ee];
    let joint = this.gamepad.joint;
    for (const action of this.held.keys()) {
      const [kind, axis, sign] = ACTIONS[action];
      if (kind === "ee") ee[axis] += sign;
      else joint += sign;
    }
    const clamp = (v) => Math.max(-1, Math.min(1, v));
    if (joint !== 0) { // a turn wins over a gripper move held at the same time (one motion per message)
      return { joint_velocity: [round3(clamp(joint) * (this.fine ? SPEEDS.jointFine : SPEEDS.joint)), 0, 0, 0] };
    }
    if (ee.some((v) => v !== 0)) {
      const speed = this.fine ? SPEEDS.eeFine : SPEEDS.ee;
      return { ee_velocity: ee.map((v) => round3(clamp(v) * speed) + 0) }; // + 0: no -0 in the JSON
    }
    return {};
  }

  /** Send the input state if it changed (or `force`), paced to the server's rate limit. */
  update(force = false) {
    if (!this.ready || (this.over && !this.over.retry)) return;
    const motion = this.motion();
    const key = JSON.stringify(motion);
    if (!force && this.gripperPending === null && key === this.sentMotion) return;
    this.lastInputAt = performance.now();
    const wait = this.pace();
    if (wait > 0) {
      clearTimeout(this.paceTimer); // the latest state is sent when the pace allows
      this.paceTimer = setTimeout(() => this.update(force), wait);
      return;
    }
    const message = { type: "input", seq: this.seq + 1, client_ms: performance.now(), ...motion };
    if (this.gripperPending !== null) message.gripper = this.gripperPending;
    this.send(message);
    this.inputSeq = message.seq;
    this.sentMotion = key;
    this.lastInputGripper = this.gripperPending;
    this.gripperPending = null;
  }

  /** Milliseconds until the next message may go (a token bucket at limits.rate_limit_hz). */
  pace() {
    const rate = (this.limits && this.limits.rate_limit_hz) || 20;
    const now = performance.now();
    this.tokens = Math.min(BURST, this.tokens + ((now - this.tokensAt) * rate) / 1000);
    this.tokensAt = now;
    if (this.tokens >= 1) return 0;
    return Math.ceil(((1 - this.tokens) * 1000) / rate);
  }

  send(message) {
    this.tokens -= 1;
    this.seq = message.seq;
    this.lastSent = { type: message.type, seq: message.seq, client_ms: message.client_ms };
    this.ws.send(JSON.stringify(message));
    this.scheduleKeepalive();
  }

  /** While a motion is held, say so at least every limits.keepalive_s, or the server's dead-man stops it. */
  scheduleKeepalive() {
    clearTimeout(this.keepaliveTimer);
    if (!this.moving() || !this.limits) return;
    this.keepaliveTimer = setTimeout(() => {
      if (!this.ready || !this.moving()) return;
      this.send({ type: "keepalive", seq: this.seq + 1, client_ms: performance.now() });
    }, this.limits.keepalive_s * 1000);
  }
}
