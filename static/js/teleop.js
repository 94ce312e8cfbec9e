// Teleoperation: held keys, on-screen buttons and a gamepad become one command, sent at 30 Hz
// over the websocket /api/p/{token}/teleop while something is held (and while the world needs
// time to settle: fingers moving, an item falling). The server owns the arm; the page shows
// what the acks say (gripper, item).

const SEND_MS = 1000 / 30;
const MIN_GAP_MS = 15; // the server takes 60 commands/s with a small burst
const EE_SPEED = 0.2; // m/s per axis (server maximum 0.3)
const EE_SPEED_FINE = 0.025;
const JOINT_SPEED = 0.6; // rad/s (server maximum 1.2)
const JOINT_SPEED_FINE = 0.1;
const DEADZONE = 0.15;
const GRIPPER_MAX = 0.1; // m, fully open (experiment/world/constants.py)

/** Motion actions: world-frame axis (x towards the shelf, y to the left, z up) or joint 1. */
export const ACTIONS = {
  "x+": ["ee", 0, 1], "x-": ["ee", 0, -1],
  "y+": ["ee", 1, 1], "y-": ["ee", 1, -1],
  "z+": ["ee", 2, 1], "z-": ["ee", 2, -1],
  "j1+": ["joint", 0, 1], "j1-": ["joint", 0, -1],
};

export class Teleop {
  constructor({ url, onWorld, onDone, onGone, onConnection, log }) {
    this.url = url;
    this.onWorld = onWorld;
    this.onDone = onDone;
    this.onGone = onGone;
    this.onConnection = onConnection;
    this.log = log;
    this.held = new Map(); // action -> Set of sources (key codes, button ids)
    this.fineKey = false;
    this.fineToggle = false;
    this.gripperPending = false;
    this.gamepad = { ee: [0, 0, 0], joint: 0 };
    this.ws = null;
    this.wanted = null; // trial key string while teleoperation is wanted
    this.seq = 0;
    this.ackSeq = -1;
    this.lastSend = 0;
    this.world = null;
    this.scene = null;
    this.retryMs = 500;
    this.timer = null;
    this.loop = null;
  }

  get active() {
    return this.wanted !== null;
  }

  get open() {
    return this.ws !== null && this.ws.readyState === WebSocket.OPEN;
  }

  /** Teleoperate the trial `key` (a no-op when already doing so). */
  start(key) {
    if (this.wanted === key) return;
    this.stop();
    this.wanted = key;
    this.world = null;
    this.connect();
    this.loop = setInterval(() => this.tick(false), SEND_MS);
  }

  stop() {
    this.wanted = null;
    clearInterval(this.loop);
    clearTimeout(this.timer);
    this.loop = null;
    if (this.ws) {
      const ws = this.ws;
      this.ws = null;
      ws.onclose = null;
      ws.close(1000, "trial over");
    }
    this.releaseAll();
  }

  connect() {
    const ws = new WebSocket(this.url);
    this.ws = ws;
    ws.onopen = () => {
      this.retryMs = 500;
      this.onConnection(true);
    };
    ws.onmessage = (event) => this.receive(JSON.parse(event.data));
    ws.onclose = (event) => {
      if (this.ws !== ws) return;
      this.ws = null;
      if (event.code === 4404) {
        this.wanted = null;
        this.onGone();
        return;
      }
      if (this.wanted === null) return;
      this.onConnection(false);
      this.log("teleop_disconnected", { code: event.code });
      this.timer = setTimeout(() => this.wanted !== null && this.connect(), this.retryMs);
      this.retryMs = Math.min(this.retryMs * 2, 8000);
    };
  }

  receive(message) {
    if (message.type === "hello") {
      if (message.stage !== "teleop") { // the trial moved on (or has not reached teleoperation)
        this.stop();
        this.onGone();
        return;
      }
      this.scene = message.scene || null;
      this.setWorld(message.world, []);
      return;
    }
    if (message.type !== "ack") return;
    this.lastAck = { ok: message.ok, error: message.error, events: message.events };
    this.ackSeq = Math.max(this.ackSeq, message.seq ?? -1);
    if (!message.ok) {
      if ((message.error || "").startsWith("not teleoperating")) {
        this.stop();
        this.onGone();
      }
      return;
    }
    this.setWorld(message.world, message.events || []);
    if (message.trial_done) {
      this.wanted = null;
      this.onDone();
    }
  }

  setWorld(world, events) {
    if (!world) return;
    this.world = world;
    this.onWorld(world, events);
  }

  // -- input ------------------------------------------------------------------------
  press(action, source) {
    const sources = this.held.get(action) || new Set();
    const wasIdle = !this.moving();
    sources.add(source);
    this.held.set(action, sources);
    if (wasIdle) this.tick(true); // respond at once, then at 30 Hz
  }

  release(action, source) {
    const sources = this.held.get(action);
    if (!sources) return;
    sources.delete(source);
    if (sources.size === 0) this.held.delete(action);
  }

  releaseAll() {
    this.held.clear();
    this.fineKey = false;
    this.gamepad = { ee: [0, 0, 0], joint: 0 };
  }

  toggleGripper() {
    this.gripperPending = true;
    this.tick(true);
  }

  setGamepad(ee, joint) {
    const wasIdle = !this.moving();
    this.gamepad = { ee: ee.map((v) => (Math.abs(v) < DEADZONE ? 0 : v)), joint: Math.abs(joint) < DEADZONE ? 0 : joint };
    if (wasIdle && this.moving()) this.tick(true);
  }

  get fine() {
    return this.fineKey !== this.fineToggle; // Shift inverts the on-screen "precise" toggle
  }

  moving() {
    return this.held.size > 0 || this.gamepad.ee.some((v) => v !== 0) || this.gamepad.joint !== 0;
  }

  /** The command for what is held now, or null when nothing is. */
  command() {
    const ee = [...this.gamepad.ee];
    let joint = this.gamepad.joint;
    for (const action of this.held.keys()) {
      const [kind, axis, sign] = ACTIONS[action];
      if (kind === "ee") ee[axis] += sign;
      else joint += sign;
    }
    const clamp = (v) => Math.max(-1, Math.min(1, v));
    const command = {};
    if (joint !== 0) {
      command.joint_velocity = [clamp(joint) * (this.fine ? JOINT_SPEED_FINE : JOINT_SPEED), 0, 0, 0];
    } else if (ee.some((v) => v !== 0)) {
      const speed = this.fine ? EE_SPEED_FINE : EE_SPEED;
      command.ee_velocity = ee.map((v) => clamp(v) * speed);
    }
    // "G toggles", but the wire command says which way: a sped-up server applies one command in
    // several sub-steps, and a "toggle" would then flip once per sub-step.
    if (this.gripperPending) command.gripper = this.gripperOpen() ? "close" : "open";
    return Object.keys(command).length ? command : null;
  }

  /** Open means fully open: holding an item, the gripper's target is the item's width. */
  gripperOpen() {
    return this.world === null || this.world.gripper_target >= GRIPPER_MAX - 1e-6;
  }

  /** Whether the world must keep running with no input (fingers moving, an item falling). */
  settling() {
    const w = this.world;
    return w !== null && (Math.abs(w.gripper - w.gripper_target) > 1e-4 || w.item.mode === "dropped");
  }

  tick(immediate) {
    if (!this.open) return;
    const t = performance.now();
    if (t - this.lastSend < (immediate ? MIN_GAP_MS : SEND_MS - 5)) return;
    let command = this.command();
    if (command === null && this.settling()) command = {};
    if (command === null) return;
    this.gripperPending = false;
    this.seq += 1;
    this.lastSend = t;
    this.ws.send(JSON.stringify({ seq: this.seq, command, client_ms: t }));
  }
}
