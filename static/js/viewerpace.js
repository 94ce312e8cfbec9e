// Pacing of the 3D view. The viser client in the (same-origin) iframe draws on every animation frame,
// and its frames run on this page's main thread. Where WebGL is drawn in software (no usable GPU:
// SwiftShader), a frame's cost is mostly not JavaScript but the browser drawing the canvas and reading
// it back for the compositor, which blocks the main thread — measured here at 0.3–2.5 s a frame at the
// default size, leaving the page's own timers and keys a few per cent of the thread.
//
// So the page keeps the view to a share of the main thread: it wraps the iframe window's
// requestAnimationFrame, measures what each frame costs (from its first callback until the thread is
// free again), holds the next frame back until the view has used at most `budget` of the time, and
// holds expensive frames back while the participant steers. It also reports the view's frame rate;
// the trial screen replaces a view too slow to steer by with the 2-D helper view and pauses it.
// (Drawing fewer pixels does not help much there: at a quarter of the pixels a frame still cost 60-100 %
// as much, measured with benchmarks/bench_page.py, and viser's layout changes in a small frame.)

const WINDOW_MS = 2000; // frame rate and cost are judged over windows this long
const COST_SMOOTHING = 0.3; // weight of the newest frame in the moving average of frame cost
const MAX_PAUSE_MS = 2000; // the budget never holds the view back longer than this…
const MAX_DEFER_MS = 2500; // …nor does steering (below)
const DEFER_ABOVE_MS = 40; // frames costing more than this wait while the participant steers
const BUSY_RECHECK_MS = 100;
const PAUSED_RECHECK_MS = 250;
const SAMPLE_SIZE = 8; // the canvas is looked at as SAMPLE_SIZE × SAMPLE_SIZE pixels
const SAMPLE_VARIED = 24; // ... and shows something (not one blank colour) when its pixels differ by more than this

export class ViewerPace {
  /**
   * frame: the viewer <iframe> (loaded, same-origin). budget: largest share of the main thread the view
   * may use (1: no pacing); maxFps: frame cap (0: none); busy(): whether the participant is steering now (expensive frames wait); onRate(fps, costMs) after
   * each window.
   */
  constructor(frame, { budget = 0.4, maxFps = 30, busy = () => false, onRate = () => {} } = {}) {
    this.frame = frame;
    this.busy = busy;
    this.win = frame.contentWindow;
    this.onRate = onRate;
    this.frames = 0;
    this.totalFrames = 0;
    this.busyMs = 0; // time in the view's frame callbacks (its JavaScript)
    this.costMs = null; // moving average of what a frame blocks the main thread (ms)
    this.recent = []; // the last frames' costs (ms), for a look from the console
    this.fps = null;
    this.last = -Infinity; // start of the last frame
    this.nextAt = 0; // no frame before this (the budget)
    this.paused = false;
    this.windowStart = this.win.performance.now();
    this.timers = new Map();
    this.nextId = -1;
    this.stamp = { name: null, renderSeen: null, drawnAt: null }; // the scene proof asked for (stampDrawn())
    this.sampler = null;
    this.configure({ budget, maxFps });
    this.install();
  }

  configure({ budget = this.budget, maxFps = this.maxFps, busy = null } = {}) {
    if (busy !== null) this.busy = busy;
    this.budget = budget;
    this.maxFps = maxFps;
    this.minInterval = maxFps > 0 ? 1000 / maxFps : 0;
    if (budget >= 1) this.nextAt = 0;
  }

  /**
   * Proof that the view has drawn the scene whose stamp node is `name` (a node the server creates after the rest
   * of the scene's first picture; server/viewer/scene.py): the node was in viser's three.js scene before a render
   * that has happened since, and the canvas shows something. Returns this page's performance.now() just after that
   * render (checked around each frame's callbacks, and at each call), or null while there is no such proof: a
   * frame of an earlier scene, however recent, never proves this one.
   */
  stampDrawn(name) {
    if (this.stamp.name !== name) this.stamp = { name, renderSeen: null, drawnAt: null };
    this.checkStamp();
    return this.stamp.drawnAt;
  }

  checkStamp() {
    const s = this.stamp;
    if (s.name === null || s.drawnAt !== null) return;
    const renders = this.renderCount();
    if (renders === null) return;
    if (s.renderSeen === null) {
      if (this.inScene(s.name)) s.renderSeen = renders;
    } else if (renders > s.renderSeen && this.sampleFrame()) {
      s.drawnAt = performance.now();
    }
  }

  /** Renders of viser's three.js renderer so far (three.js counts them in `info.render.frame`); null if unknown. */
  renderCount() {
    const points = this.win.__viserTestpoints;
    const info = points && points.rendererInfo;
    return info && info.render && typeof info.render.frame === "number" ? info.render.frame : null;
  }

  /** Whether the scene node `name` is attached to viser's three.js scene (what a render draws). */
  inScene(name) {
    const m = this.win.__viserMutable;
    if (!m || !m.scene || !m.nodeRefFromName) return false;
    for (let o = m.nodeRefFromName[name]; o; o = o.parent) if (o === m.scene) return true;
    return false;
  }

  /** The view's drawing canvas (the largest: the viewer also has empty helper canvases). */
  canvas() {
    let best = null;
    for (const c of this.win.document.querySelectorAll("canvas")) {
      if (c.width * c.height > (best ? best.width * best.height : 0)) best = c;
    }
    return best;
  }

  /** Whether the canvas shows something, not one blank colour (viser keeps its drawing buffer between frames). */
  sampleFrame() {
    const canvas = this.canvas();
    if (!canvas) return false;
    if (!this.sampler) {
      this.sampler = this.win.document.createElement("canvas");
      this.sampler.width = SAMPLE_SIZE;
      this.sampler.height = SAMPLE_SIZE;
    }
    const g = this.sampler.getContext("2d", { willReadFrequently: true });
    g.clearRect(0, 0, SAMPLE_SIZE, SAMPLE_SIZE);
    g.drawImage(canvas, 0, 0, SAMPLE_SIZE, SAMPLE_SIZE);
    const px = g.getImageData(0, 0, SAMPLE_SIZE, SAMPLE_SIZE).data;
    let lo = 255 * 3;
    let hi = 0;
    for (let i = 0; i < px.length; i += 4) {
      const v = px[i] + px[i + 1] + px[i + 2];
      lo = Math.min(lo, v);
      hi = Math.max(hi, v);
    }
    return hi - lo > SAMPLE_VARIED;
  }

  /** A paused view draws nothing (the page shows something else in its place). */
  setPaused(paused) {
    this.paused = paused;
  }

  install() {
    const win = this.win;
    const raf = win.requestAnimationFrame.bind(win);
    const cancel = win.cancelAnimationFrame.bind(win);
    const channel = new win.MessageChannel();
    let frameTs = null;
    let frameStart = 0;
    // A message posted during a frame is handled once the browser has finished that frame's work.
    channel.port1.onmessage = () => this.frameDone(win.performance.now() - frameStart);
    this.nativeRaf = raf;
    const run = (cb) => (ts) => {
      const start = win.performance.now();
      if (ts !== frameTs) { // several callbacks run in one frame: count the frame once
        frameTs = ts;
        frameStart = start;
        this.last = start;
        channel.port2.postMessage(0);
        this.count(start);
      }
      const proving = this.stamp.name !== null && this.stamp.drawnAt === null;
      if (proving) this.checkStamp(); // the stamp in the scene before a render…
      cb(ts);
      this.busyMs += win.performance.now() - start;
      if (proving) this.checkStamp(); // …and a render since: the time is the render's
    };
    // A held-back frame is looked at again when its time comes (the input may still be busy then).
    const schedule = (id, cb) => {
      const wait = this.wait();
      if (wait <= 4) {
        this.timers.delete(id);
        raf(run(cb));
        return;
      }
      this.timers.set(id, win.setTimeout(() => schedule(id, cb), wait));
    };
    win.requestAnimationFrame = (cb) => {
      if (this.wait() <= 4) return raf(run(cb));
      const id = this.nextId; // negative ids are ours, never the browser's
      this.nextId -= 1;
      schedule(id, cb);
      return id;
    };
    win.cancelAnimationFrame = (id) => {
      if (id < 0) {
        win.clearTimeout(this.timers.get(id));
        this.timers.delete(id);
      } else {
        cancel(id);
      }
    };
  }

  /** Milliseconds until the view may draw its next frame. */
  wait() {
    if (this.paused) return PAUSED_RECHECK_MS;
    const now = this.win.performance.now();
    let wait = Math.max(this.last + this.minInterval, this.nextAt) - now;
    // Expensive frames wait while the participant is steering (a key held, or just changed): a frame
    // started now would block the thread for its whole cost, and the key's release with it.
    if (this.costMs !== null && this.costMs > DEFER_ABOVE_MS && now - this.last < MAX_DEFER_MS && this.busy()) {
      wait = Math.max(wait, BUSY_RECHECK_MS);
    }
    return wait;
  }

  /** A frame took `cost` ms of the main thread: the next one waits until that is `budget` of the time. */
  frameDone(cost) {
    this.recent.push(Math.round(cost));
    if (this.recent.length > 20) this.recent.shift();
    this.costMs = this.costMs === null ? cost : this.costMs + COST_SMOOTHING * (cost - this.costMs);
    if (this.budget >= 1) return;
    // A frame that waited behind other work (or the view's start-up) must not freeze the view for long.
    const pause = Math.min(MAX_PAUSE_MS, (cost * (1 - this.budget)) / this.budget);
    this.nextAt = this.win.performance.now() + pause;
  }

  count(now) {
    this.frames += 1;
    this.totalFrames += 1;
    const span = now - this.windowStart;
    if (span < WINDOW_MS) return;
    this.fps = (this.frames * 1000) / span;
    this.frames = 0;
    this.windowStart = now;
    this.onRate(this.fps, this.costMs);
  }
}
