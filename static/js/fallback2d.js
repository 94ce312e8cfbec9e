// The 2-D helper view: the teleoperation seen from above and from the robot's right side, drawn on a
// <canvas> from the socket's hello.teleop.scene and each world message. It stands in for the 3D view
// when that cannot load or cannot keep up, and anyone may switch it on. Drawing it costs well under a
// millisecond, so it stays usable on a machine that cannot draw the 3D view.

import { t } from "./i18n.js";

// Robot body sizes for the drawing only (experiment/world/constants.py; not part of the protocol).
const BASE_SIZE = [0.56, 0.48]; // length (x), width (y)
const BASE_TOP = 0.34;
const MAST_XY = [0.18, -0.10]; // mast axis in the base frame
const SHOULDER_Z = 1.05;
const UPPER_ARM = 0.5;
const FOREARM = 0.45;
const TOOL_LENGTH = 0.14; // wrist joint to the gripper's centre, pointing down
const Z_TOP = 1.45; // the side view shows heights 0 .. Z_TOP m

const C = {
  bg: "#f7f8fa", panel: "#ffffff", frame: "#9aa3ad", text: "#1b1f24", muted: "#4a5360",
  shelf: "#b08a60", shelfLine: "#6e5335", obstacle: "#c8322d", item: "#a3acb6", itemLine: "#6b7480",
  bin: "#2f6f3e", binFill: "#d7eedc", robot: "#c9ced6", robotLine: "#59626e", arm: "#3b4652",
  gripper: "#0b57d0", grasp: "#146c2e", target: "#e07b00", clear: "#7a4fb5",
};
const NAMED = { // WorldView colours by name, in case the scene names them
  "dark yellow": "rgb(230,160,30)", blue: "rgb(60,140,210)", green: "rgb(90,170,80)", pink: "rgb(220,90,140)",
  yellow: "rgb(240,220,80)", purple: "rgb(130,90,190)", orange: "rgb(240,120,60)", turquoise: "rgb(70,190,190)",
};

function cssColor(value) {
  if (typeof value !== "string") return C.target;
  if (/^(#|rgb|hsl)/i.test(value)) return value;
  return NAMED[value.toLowerCase()] || C.target;
}

/** Corner points (x, y) of a box's footprint rotated by yaw about its centre. */
function footprint(cx, cy, sx, sy, yaw = 0) {
  const c = Math.cos(yaw);
  const s = Math.sin(yaw);
  return [[-1, -1], [1, -1], [1, 1], [-1, 1]].map(([u, v]) => {
    const dx = (u * sx) / 2;
    const dy = (v * sy) / 2;
    return [cx + c * dx - s * dy, cy + s * dx + c * dy];
  });
}

/** One panel: world (a, b) -> canvas pixels with one scale for both axes, fitted into a rectangle. */
class Panel {
  constructor(rect, range, map) {
    const [a0, a1, b0, b1] = range;
    this.map = map; // world point -> [a, b] (a to the right, b up on screen)
    this.scale = Math.min(rect.w / (a1 - a0), rect.h / (b1 - b0));
    this.ox = rect.x + (rect.w - (a1 - a0) * this.scale) / 2 - a0 * this.scale;
    this.oy = rect.y + rect.h - (rect.h - (b1 - b0) * this.scale) / 2 + b0 * this.scale;
    this.rect = rect;
  }

  px(p) {
    const [a, b] = this.map(p);
    return [this.ox + a * this.scale, this.oy - b * this.scale];
  }

  /** The point clamped into the panel, and whether it had to be. */
  clamped(p) {
    const [x, y] = this.px(p);
    const r = this.rect;
    const cx = Math.min(r.x + r.w - 6, Math.max(r.x + 6, x));
    const cy = Math.min(r.y + r.h - 6, Math.max(r.y + 6, y));
    return [cx, cy, cx !== x || cy !== y];
  }
}

export class Helper2D {
  constructor(canvas) {
    this.canvas = canvas;
    this.scene = null;
    this.world = null;
    this.guidance = null;
    this.pending = false;
    this.draws = 0;
    this.drawnScene = null; // the scene last drawn in full (with a world), for "is the trial's scene on screen"
    this.drawnAt = null; // performance.now() when it was drawn
  }

  setScene(scene) {
    this.scene = scene;
    this.bounds = scene ? sceneBounds(scene) : null;
    this.request();
  }

  update(world, guidance) {
    this.world = world;
    this.guidance = guidance;
    this.request();
  }

  /** Draw at the next frame of this page (several world messages in one frame draw once). */
  request() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.draw();
    });
  }

  draw() {
    const canvas = this.canvas;
    const w = canvas.clientWidth;
    const h = canvas.clientHeight;
    if (w === 0 || h === 0) return; // hidden
    const ratio = Math.min(2, window.devicePixelRatio || 1);
    if (canvas.width !== Math.round(w * ratio) || canvas.height !== Math.round(h * ratio)) {
      canvas.width = Math.round(w * ratio);
      canvas.height = Math.round(h * ratio);
    }
    const g = canvas.getContext("2d");
    this.draws += 1;
    if (!this.scene || !this.world) {
      g.setTransform(ratio, 0, 0, ratio, 0, 0);
      g.fillStyle = C.bg;
      g.fillRect(0, 0, w, h);
      text(g, t("helper2d.waiting"), 12, 22, C.muted, 14);
      return;
    }
    // What does not move (shelf, boxes, frames, labels) is drawn once per size into a layer: a world
    // message then costs a copy and a few shapes, which matters where the page is short of CPU.
    const layout = this.layout(w, h, ratio);
    g.setTransform(1, 0, 0, 1, 0, 0);
    g.drawImage(layout.layer, 0, 0);
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    this.drawTopMoving(g, layout.top, layout.font);
    this.drawSideMoving(g, layout.side, layout.font);
    if (this.drawnScene !== this.scene) this.drawnAt = performance.now();
    this.drawnScene = this.scene;
  }

  layout(w, h, ratio) {
    const key = `${w}x${h}@${ratio}`;
    if (this.cached && this.cached.key === key && this.cached.scene === this.scene) return this.cached;
    const font = w > 600 ? 13 : 11;
    const legendH = font + 10;
    const gap = 10;
    const half = (w - 3 * gap) / 2;
    const topRect = { x: gap, y: font + 14, w: half, h: h - font - 18 - legendH };
    const sideRect = { x: 2 * gap + half, y: font + 14, w: half, h: topRect.h };
    const [x0, x1, y0, y1] = this.bounds.top;
    // From above with the shelf at the top: world x up the screen, world y (to the robot's left) to the left.
    const top = new Panel(topRect, [-y1, -y0, x0, x1], (p) => [-p[1], p[0]]);
    // From the robot's right side: world x to the right (shelf on the right), z up.
    const side = new Panel(sideRect, [x0, x1, 0, Z_TOP], (p) => [p[0], p[2]]);
    const layer = document.createElement("canvas");
    layer.width = Math.round(w * ratio);
    layer.height = Math.round(h * ratio);
    const g = layer.getContext("2d");
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.fillStyle = C.bg;
    g.fillRect(0, 0, w, h);
    this.drawTopStill(g, top, font);
    this.drawSideStill(g, side, font);
    this.legend(g, gap, h - legendH + 4, w - 2 * gap, font);
    this.cached = { key, scene: this.scene, layer, top, side, font };
    return this.cached;
  }

  drawTopStill(g, panel, font) {
    frame(g, panel.rect, t("helper2d.from_above"), font);
    const s = this.scene;
    const box = (b, fill, line) => poly(g, panel, footprint(b.center[0], b.center[1], b.size[0], b.size[1]), fill, line);
    for (const b of s.shelf) box(b, C.shelf, C.shelfLine);
    for (const b of s.other_items) box(b, C.item, C.itemLine);
    for (const b of s.obstacles) box(b, C.obstacle, "#7d1d1a");
  }

  drawTopMoving(g, panel, font) {
    const w = this.world;
    clip(g, panel.rect, () => {
      this.robotTop(g, panel);
      this.binTop(g, panel);
      this.itemTop(g, panel);
      line(g, panel.px(mastXY(w.base)), panel.px(w.tcp), C.arm, 5);
    });
    this.gripper(g, panel, w.tcp, font);
  }

  drawSideStill(g, panel, font) {
    const [x0, x1] = this.bounds.top;
    frame(g, panel.rect, t("helper2d.from_side"), font);
    const s = this.scene;
    const sideBox = (b, fill, stroke) => {
      const [cx, , cz] = b.center;
      const [sx, , sz] = b.size;
      poly(g, panel, [[cx - sx / 2, 0, cz - sz / 2], [cx + sx / 2, 0, cz - sz / 2], [cx + sx / 2, 0, cz + sz / 2],
        [cx - sx / 2, 0, cz + sz / 2]], fill, stroke);
    };
    line(g, panel.px([x0, 0, 0]), panel.px([x1, 0, 0]), C.frame, 2); // floor
    for (const b of s.shelf) sideBox(b, C.shelf, C.shelfLine);
    for (const b of s.other_items) sideBox(b, C.item, C.itemLine);
    for (const b of s.obstacles) sideBox(b, C.obstacle, "#7d1d1a");
    // The height at which a carried item clears the boxes and the bin.
    const [lx, ly] = panel.px([x0, 0, s.clear_height]);
    g.setLineDash([6, 4]);
    line(g, [lx, ly], panel.px([x1, 0, s.clear_height]), C.clear, 1.5);
    g.setLineDash([]);
    text(g, t("helper2d.safe_height"), lx + 4, ly - 4, C.clear, font - 1);
  }

  drawSideMoving(g, panel, font) {
    clip(g, panel.rect, () => {
      this.robotSide(g, panel);
      this.itemSide(g, panel);
      this.armSide(g, panel);
    });
    this.gripper(g, panel, this.world.tcp, font);
  }

  robotTop(g, panel) {
    const [bx, by, yaw] = this.world.base;
    poly(g, panel, footprint(bx, by, BASE_SIZE[0], BASE_SIZE[1], yaw), C.robot, C.robotLine);
    dot(g, panel.px(mastXY(this.world.base)), 5, C.robotLine);
  }

  binTop(g, panel) {
    const b = this.scene.bin;
    const carrying = this.world.item.mode === "grasped";
    const pts = footprint(b.opening_center[0], b.opening_center[1], b.opening_size[0], b.opening_size[1], b.yaw);
    poly(g, panel, pts, carrying ? C.binFill : "#eef3ef", C.bin, carrying ? 3 : 2);
    const [x, y] = panel.px(b.opening_center);
    text(g, t("helper2d.bin"), x - 9, y + 4, C.bin, 12, true);
  }

  robotSide(g, panel) {
    const [bx, , yaw] = this.world.base;
    const half = (Math.abs(Math.cos(yaw)) * BASE_SIZE[0] + Math.abs(Math.sin(yaw)) * BASE_SIZE[1]) / 2;
    poly(g, panel, [[bx - half, 0, 0.04], [bx + half, 0, 0.04], [bx + half, 0, BASE_TOP], [bx - half, 0, BASE_TOP]],
      C.robot, C.robotLine);
    const [mx] = mastXY(this.world.base);
    line(g, panel.px([mx, 0, BASE_TOP]), panel.px([mx, 0, SHOULDER_Z]), C.robotLine, 6);
    const b = this.scene.bin;
    const bx0 = b.opening_center[0] - b.opening_size[0] / 2;
    const bx1 = b.opening_center[0] + b.opening_size[0] / 2;
    const carrying = this.world.item.mode === "grasped";
    poly(g, panel, [[bx0, 0, BASE_TOP], [bx1, 0, BASE_TOP], [bx1, 0, b.rim_z], [bx0, 0, b.rim_z]],
      carrying ? C.binFill : "#eef3ef", C.bin, carrying ? 3 : 2);
  }

  itemTop(g, panel) {
    const t = this.scene.target;
    const p = this.world.item.position;
    const color = cssColor(t.color);
    if (t.shape === "can") {
      circle(g, panel.px(p), (t.size[0] / 2) * panel.scale, color, "#1b1f24", 1.5);
    } else {
      poly(g, panel, footprint(p[0], p[1], t.size[0], t.size[1]), color, "#1b1f24", 1.5);
    }
    this.highlight(g, panel.px(p), (Math.max(t.size[0], t.size[1]) / 2) * panel.scale + 5);
    if (this.world.item.mode === "on_shelf") cross(g, panel.px(t.grasp_point), 6, C.grasp);
  }

  itemSide(g, panel) {
    const t = this.scene.target;
    const p = this.world.item.position;
    const [hx, hz] = [t.size[0] / 2, t.size[2] / 2];
    poly(g, panel, [[p[0] - hx, 0, p[2] - hz], [p[0] + hx, 0, p[2] - hz], [p[0] + hx, 0, p[2] + hz],
      [p[0] - hx, 0, p[2] + hz]], cssColor(t.color), "#1b1f24", 1.5);
    this.highlight(g, panel.px(p), hz * panel.scale + 5);
    if (this.world.item.mode === "on_shelf") cross(g, panel.px(t.grasp_point), 6, C.grasp);
  }

  highlight(g, [x, y], r) {
    g.strokeStyle = C.target;
    g.lineWidth = 2.5;
    g.beginPath();
    g.arc(x, y, r, 0, 2 * Math.PI);
    g.stroke();
  }

  /** The arm in the side view: shoulder -> elbow (elbow up) -> wrist above the gripper. */
  armSide(g, panel) {
    const w = this.world;
    const [mx, my] = mastXY(w.base);
    const shoulder = [mx, my, SHOULDER_Z];
    const wrist = [w.tcp[0], w.tcp[1], w.tcp[2] + TOOL_LENGTH];
    const elbow = elbowUp(shoulder, wrist);
    const pts = [shoulder, elbow, wrist, w.tcp].map((p) => panel.px(p));
    for (let i = 0; i < 3; i += 1) line(g, pts[i], pts[i + 1], C.arm, i === 2 ? 3 : 5);
  }

  /** The gripper: a ring (open) or a filled dot (closed), green when closing now would grasp. */
  gripper(g, panel, tcp, font) {
    const [x, y, outside] = panel.clamped(tcp);
    const closed = this.world.gripper_target < 0.1 - 1e-6;
    const color = this.guidance && (this.guidance.can_grasp || this.guidance.over_bin) ? C.grasp : C.gripper;
    g.lineWidth = 3;
    g.strokeStyle = color;
    g.fillStyle = color;
    g.beginPath();
    g.arc(x, y, 7, 0, 2 * Math.PI);
    if (closed) g.fill();
    else g.stroke();
    const label = outside ? t("helper2d.gripper_off_view") : t("helper2d.gripper");
    g.font = `600 ${font - 1}px system-ui, sans-serif`;
    const width = g.measureText(label).width;
    const right = panel.rect.x + panel.rect.w;
    const lx = x + 10 + width > right ? x - 10 - width : x + 10; // keep the label inside the panel
    text(g, label, lx, y - 8, color, font - 1, true);
  }

  legend(g, x, y, w, font) {
    const items = [[t("helper2d.legend.item"), C.target, "ring"], [t("helper2d.legend.gripper"), C.gripper, "ring"],
      [t("helper2d.legend.grasp"), C.grasp, "cross"], [t("helper2d.legend.obstacles"), C.obstacle, "box"],
      [t("helper2d.bin"), C.bin, "box"]];
    g.font = `${font - 1}px system-ui, sans-serif`;
    let cx = x;
    for (const [label, color, kind] of items) {
      if (kind === "ring") circle(g, [cx + 6, y + font / 2 - 1], 5, null, color, 2);
      else if (kind === "cross") cross(g, [cx + 6, y + font / 2 - 1], 5, color);
      else { g.fillStyle = color; g.fillRect(cx + 1, y, 10, font - 2); }
      text(g, label, cx + 15, y + font - 2, C.text, font - 1);
      cx += 24 + g.measureText(label).width;
      if (cx > x + w) break;
    }
  }
}

/** Top-view extents (x0, x1, y0, y1) of everything in the scene, with a margin. */
function sceneBounds(scene) {
  const xs = [];
  const ys = [];
  const add = (b) => {
    xs.push(b.center[0] - b.size[0] / 2, b.center[0] + b.size[0] / 2);
    ys.push(b.center[1] - b.size[1] / 2, b.center[1] + b.size[1] / 2);
  };
  [...scene.shelf, ...scene.obstacles, ...scene.other_items, scene.target].forEach(add);
  const bin = scene.bin.opening_center;
  // The parked base stands behind the bin: leave room for it (about its length behind the opening).
  xs.push(bin[0] - 0.45, bin[0] + 0.2);
  ys.push(bin[1] - 0.35, bin[1] + 0.35);
  const m = 0.08;
  return { top: [Math.min(...xs) - m, Math.max(...xs) + m, Math.min(...ys) - m, Math.max(...ys) + m] };
}

function mastXY([x, y, yaw]) {
  const c = Math.cos(yaw);
  const s = Math.sin(yaw);
  return [x + c * MAST_XY[0] - s * MAST_XY[1], y + s * MAST_XY[0] + c * MAST_XY[1]];
}

function elbowUp(a, b) {
  const d = Math.hypot(b[0] - a[0], b[1] - a[1], b[2] - a[2]);
  const reach = Math.min(d, UPPER_ARM + FOREARM - 1e-6);
  const along = (UPPER_ARM ** 2 - FOREARM ** 2 + reach ** 2) / (2 * reach);
  const up = Math.sqrt(Math.max(0, UPPER_ARM ** 2 - along ** 2));
  const u = [(b[0] - a[0]) / d, (b[1] - a[1]) / d, (b[2] - a[2]) / d];
  // The upward direction perpendicular to u in the vertical plane through a and b.
  const horiz = Math.hypot(u[0], u[1]) || 1e-9;
  const n = [(-u[2] * u[0]) / horiz, (-u[2] * u[1]) / horiz, horiz];
  return [0, 1, 2].map((i) => a[i] + along * u[i] + up * n[i]);
}

// -- drawing primitives ---------------------------------------------------------------------------
/** Draw inside a panel only (an arm reaching out of the view is cut at its edge). */
function clip(g, rect, draw) {
  g.save();
  g.beginPath();
  g.rect(rect.x + 1, rect.y + 1, rect.w - 2, rect.h - 2);
  g.clip();
  draw();
  g.restore();
}

function frame(g, rect, title, font) {
  g.fillStyle = C.panel;
  g.fillRect(rect.x, rect.y, rect.w, rect.h);
  g.strokeStyle = C.frame;
  g.lineWidth = 1;
  g.strokeRect(rect.x + 0.5, rect.y + 0.5, rect.w - 1, rect.h - 1);
  text(g, title, rect.x, rect.y - 5, C.text, font, true);
}

function poly(g, panel, pts, fill, stroke, width = 1) {
  g.beginPath();
  pts.forEach((p, i) => {
    const [x, y] = panel.px(p);
    if (i === 0) g.moveTo(x, y);
    else g.lineTo(x, y);
  });
  g.closePath();
  if (fill) {
    g.fillStyle = fill;
    g.fill();
  }
  if (stroke) {
    g.strokeStyle = stroke;
    g.lineWidth = width;
    g.stroke();
  }
}

function line(g, [x0, y0], [x1, y1], color, width) {
  g.strokeStyle = color;
  g.lineWidth = width;
  g.lineCap = "round";
  g.beginPath();
  g.moveTo(x0, y0);
  g.lineTo(x1, y1);
  g.stroke();
}

function circle(g, [x, y], r, fill, stroke, width = 1) {
  g.beginPath();
  g.arc(x, y, Math.max(2, r), 0, 2 * Math.PI);
  if (fill) {
    g.fillStyle = fill;
    g.fill();
  }
  if (stroke) {
    g.strokeStyle = stroke;
    g.lineWidth = width;
    g.stroke();
  }
}

function dot(g, p, r, color) {
  circle(g, p, r, color, null);
}

function cross(g, [x, y], r, color) {
  line(g, [x - r, y], [x + r, y], color, 2);
  line(g, [x, y - r], [x, y + r], color, 2);
}

function text(g, value, x, y, color, size, bold = false) {
  g.font = `${bold ? "600 " : ""}${size}px system-ui, -apple-system, "Segoe UI", Roboto, sans-serif`;
  g.fillStyle = color;
  g.fillText(value, x, y);
}
