"""Teleoperation physics: microseconds per substep of ``hold_command`` on recorded trajectories.

Run: ``python benchmarks/bench_physics.py [--rev REV] [--seeds 3] [--repeat 7] [--json]``.

The server integrates every teleoperated arm 30 times a second with ``hold_command(state, scene, command,
duration)``, one ``_step`` per 1/30 s of simulated time. This benchmark records, with the current code,
the calls of several kinds of teleoperation in low and high complexity scenes (``--seeds`` of each):

- ``free``: random smooth TCP velocities (and a few j1 turns and gripper toggles) in the free space in
  front of the shelf;
- ``grasp``: the scripted teleoperator (``scripted_teleop_commands``) from the start until it grasps;
- ``carry``: the same run from the grasp until the item lies in the bin;
- ``push``: pushing into things so that "blocked" happens: the fingers down onto an obstacle (high) or
  the lower board's front (low), into the shelf from the grasp pose, the shoulder swung down;
- ``slide``: moving along an obstacle's top or a board just above it (free but close), then diagonally
  into it (blocked);
- ``contact``: from a pose already in contact with it (fingertips 3 mm into it), along it and out of it
  (sliding along an existing contact is allowed). The server's arms start free and never get there: this
  checks the rule.

Each call's duration is drawn around 1/30 s (0.025 to 0.045 s: sometimes two substeps), as the server's
clock does. Each trajectory is replayed in order (``--repeat`` times, in a fresh copy of its scene whose
static collision data is built first; as on the server, each call gets the state the previous call
returned) and timed; printed: us per substep, median over repetitions, per kind and complexity, with the
calls that reported "blocked".

``--rev REV`` also loads ``experiment/world`` of git revision REV (``git archive`` into a temporary
folder, imported under another name), times it back to back with the current code (alternating, same
trajectories) and checks that both return equal states and events on every call of every trajectory
(bit for bit; otherwise the largest difference is printed and the exit status is 1).
"""

from __future__ import annotations

import argparse
import importlib
import io
import json
import math
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.results_log import append_result  # noqa: E402 -- after the sys.path edit that makes benchmarks/ importable

KINDS = ("free", "grasp", "carry", "push", "slide", "contact")


def load_world(rev: str | None) -> SimpleNamespace:
    """The world package of git revision ``rev`` (None: the working tree's), as a namespace."""
    if rev is None:
        pkg = "experiment"
    else:
        sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", f"{rev}^{{commit}}"],
                             capture_output=True, text=True, check=True).stdout.strip()
        pkg = f"_bench_world_{sha[:12]}"
        tmp = Path(tempfile.mkdtemp(prefix="bench_physics_"))
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", sha, "experiment/world"],
                                 capture_output=True, check=True).stdout
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(tmp, filter="data")
        (tmp / "experiment").rename(tmp / pkg)
        (tmp / pkg / "__init__.py").write_text("")
        for f in (tmp / pkg / "world").glob("*.py"):
            f.write_text(f.read_text().replace("experiment.world", f"{pkg}.world"))
        sys.path.insert(0, str(tmp))
    mod = {name: importlib.import_module(f"{pkg}.world.{name}")
           for name in ("collision", "scene", "state", "teleop", "scripted", "robot", "path")}
    return SimpleNamespace(
        name=rev or "current", build_scene=mod["scene"].build_scene, collisions=mod["collision"].collisions,
        teleop_start_state=mod["teleop"].teleop_start_state, hold_command=mod["teleop"].hold_command,
        TeleopCommand=mod["teleop"].TeleopCommand, WorldState=mod["state"].WorldState,
        ItemState=mod["state"].ItemState, ItemMode=mod["state"].ItemMode, HOLD_SUBSTEP=mod["teleop"].HOLD_SUBSTEP)


# --- trajectories (recorded with the current code) -----------------------------------------------

@dataclass
class Trajectory:
    kind: str
    complexity: str
    seed: int
    calls: list = field(default_factory=list)  # (state, command, duration)
    chained: list = field(default_factory=list)  # per call: its state is the previous call's result
    blocked: int = 0  # calls that reported "blocked"


class Recorder:
    """Runs ``hold_command`` of the current code and keeps every call."""

    def __init__(self, w, traj: Trajectory, rng: np.random.Generator):
        self.w, self.traj, self.rng = w, traj, rng
        self.scene = w.build_scene(traj.complexity, traj.seed)
        self.state = w.teleop_start_state(self.scene)
        self.last = None

    def call(self, command, duration: float | None = None) -> tuple[str, ...]:
        duration = float(self.rng.uniform(0.025, 0.045)) if duration is None else duration
        self.traj.chained.append(self.state is self.last)
        self.traj.calls.append((self.state, command, duration))
        self.state, events = self.w.hold_command(self.state, self.scene, command, duration)
        self.last = self.state
        self.traj.blocked += "blocked" in events
        return events

    def tcp(self) -> np.ndarray:
        from experiment.world.robot import tcp_position
        return tcp_position(self.state.base, self.state.joints)

    def ee(self, v, gripper=None):
        return self.w.TeleopCommand(ee_velocity=tuple(float(x) for x in v), gripper=gripper)

    def go_to(self, goal, limit: float = 4.0, tol: float = 0.004) -> None:
        """Proportional TCP moves towards ``goal`` until within tol (or blocked for long, or time out)."""
        end = self.state.t + limit
        while self.state.t < end:
            e = np.asarray(goal, dtype=float) - self.tcp()
            n = float(np.linalg.norm(e))
            if n < tol:
                return
            self.call(self.ee(e * min(4.0, 0.3 / n)))

    def hold(self, command, seconds: float) -> None:
        end = self.state.t + seconds
        while self.state.t < end:
            self.call(command)

    def scripted(self, until) -> None:
        from experiment.world.scripted import scripted_teleop_commands
        end = self.state.t + 25.0
        while not until(self) and self.state.t < end:
            self.call(scripted_teleop_commands(self.state, self.scene))


def record_free(rec: Recorder) -> None:
    from experiment.world import constants as K
    from experiment.world.robot import mast_xy
    mx, my = mast_xy(rec.state.base)
    floor = max([0.95] + [float(ob.hi[2]) + 0.1 for ob in rec.scene.obstacles])  # fingertips over the obstacles
    lo = np.array([mx + 0.15, my - 0.35, floor])
    hi = np.array([K.SHELF_FRONT_X - 0.15, my + 0.35, 1.30])
    v = np.zeros(3)
    for i in range(300):
        if i % 60 == 59:
            rec.call(rec.w.TeleopCommand(gripper="toggle"))
            continue
        if 100 <= i < 115:
            rec.call(rec.w.TeleopCommand(joint_velocity=(0.6 if i < 108 else -0.6, 0.0, 0.0, 0.0)))
            continue
        v = 0.85 * v + rec.rng.normal(0.0, 0.08, 3)
        tcp = rec.tcp()
        v += np.where(tcp < lo, 0.1, 0.0) - np.where(tcp > hi, 0.1, 0.0)
        n = float(np.linalg.norm(v))
        if n > 0.3:
            v *= 0.3 / n
        rec.call(rec.ee(v))


def record_grasp_carry(rec: Recorder, grasp: Trajectory, carry: Trajectory) -> None:
    mode = rec.w.ItemMode
    rec.traj = grasp
    rec.scripted(lambda r: r.state.item.mode == mode.GRASPED)
    rec.traj = carry
    rec.scripted(lambda r: r.state.item.mode == mode.IN_BIN and r.state.item.position[2] <= r.state.item.rest_z)


def _above_contact_target(scene):
    """(x, y, top z, sideways extent) of the thing the fingers are pushed onto."""
    from experiment.world import constants as K
    if scene.obstacles:
        ob = scene.obstacles[0]
        return float(ob.center[0]), float(ob.center[1]), float(ob.hi[2]), float(ob.size[1]) / 2
    # the lower board's strip in front of the items
    return K.SHELF_FRONT_X + 0.03, float(scene.target.center[1]), K.LOWER_BOARD_TOP, 0.1


def record_push(rec: Recorder) -> None:
    from experiment.world import constants as K
    x, y, top, _ = _above_contact_target(rec.scene)
    rec.go_to((x, y, max(top + 0.15, 0.6) if rec.scene.obstacles else 0.95))
    rec.go_to((x, y, top + 0.08), limit=3.0)
    rec.hold(rec.ee((0.0, 0.0, -0.3)), 1.0)  # fingers onto the top: blocked
    rec.go_to((x, y, 0.95 if not rec.scene.obstacles else top + 0.15))
    # into the shelf from above the target's grasp point
    from experiment.world.scripted import scripted_teleop_commands
    end = rec.state.t + 10.0
    while rec.state.item.mode == rec.w.ItemMode.ON_SHELF and rec.state.t < end:
        cmd = scripted_teleop_commands(rec.state, rec.scene)
        if cmd.gripper == "close":
            break
        rec.call(cmd)
    rec.hold(rec.ee((0.0, 0.0, -0.3)), 0.7)  # fingers down past the item: board / item
    rec.hold(rec.ee((0.3, 0.0, 0.0)), 0.7)  # forward into the item / back
    rec.hold(rec.ee((0.0, 0.3, 0.0)), 0.7)  # sideways into the neighbours
    rec.go_to(np.add(rec.tcp(), (0.0, 0.0, 0.25)))
    rec.hold(rec.w.TeleopCommand(joint_velocity=(0.0, -1.0, 0.5, 0.0)), 1.5)  # shoulder down: blocked
    assert K.MAX_JOINT_SPEED > 0


def record_slide(rec: Recorder) -> None:
    x, y, top, half = _above_contact_target(rec.scene)
    rec.go_to((x, y, max(top + 0.15, 0.6) if rec.scene.obstacles else 0.95))
    rec.go_to((x, y, top + 0.06), limit=3.0)
    rec.hold(rec.ee((0.0, 0.0, -0.1)), 0.6)  # down until blocked: just above the top
    for vy in (0.1, -0.1, 0.1):  # along the top, close to it
        rec.hold(rec.ee((0.0, vy, 0.0)), 0.5 * half / 0.1)
    rec.hold(rec.ee((0.0, 0.1, -0.1)), 0.5)  # diagonally into it: blocked
    rec.hold(rec.ee((0.1, 0.0, 0.0)), 0.5)


def record_contact(rec: Recorder) -> None:
    """From a pose already in contact (fingertips 3 mm into the top): along it, and up out of it."""
    from dataclasses import replace

    from experiment.world import constants as K
    from experiment.world.robot import solve_ik
    x, y, top, half = _above_contact_target(rec.scene)
    tip = K.FINGER_LENGTH - K.TCP_OFFSET
    joints = solve_ik(rec.state.base, (x, y - half / 2, top + tip - 0.003))
    assert joints is not None, "the point above the contact is reachable"
    rec.state = replace(rec.state, joints=tuple(joints.tolist()))
    assert rec.w.collisions(rec.state, rec.scene)
    rec.hold(rec.ee((0.0, 0.1, 0.0)), 0.4)
    rec.hold(rec.ee((0.0, -0.1, 0.0)), 0.4)
    rec.hold(rec.ee((0.0, 0.05, 0.05)), 0.4)


def record_all(w, seeds: int) -> list[Trajectory]:
    trajectories: list[Trajectory] = []
    for complexity in ("low", "high"):
        for seed in range(seeds):
            rng = np.random.default_rng([seed, complexity == "high"])
            traj = {k: Trajectory(k, complexity, seed) for k in KINDS}
            record_free(Recorder(w, traj["free"], rng))
            rec = Recorder(w, traj["grasp"], rng)
            record_grasp_carry(rec, traj["grasp"], traj["carry"])
            record_push(Recorder(w, traj["push"], rng))
            record_slide(Recorder(w, traj["slide"], rng))
            record_contact(Recorder(w, traj["contact"], rng))
            trajectories += traj.values()
    return trajectories


# --- replay ---------------------------------------------------------------------------------------

def substeps(duration: float, substep: float) -> int:
    n, remaining = 0, float(duration)
    while remaining > 1e-9:
        remaining -= min(remaining, substep)
        n += 1
    return n


def convert(w, state, command):
    """A recorded (current code) state and command as objects of world package ``w``."""
    it = state.item
    item = w.ItemState(w.ItemMode(it.mode.value), it.position, it.wxyz, it.since, it.grip, it.fall_from,
                       it.rest_z)
    return (w.WorldState(state.t, state.base, state.joints, state.gripper, state.gripper_target, item),
            w.TeleopCommand(command.ee_velocity, command.joint_velocity, command.gripper))


def plain(state, events) -> tuple:
    it = state.item
    return ((state.t, state.base, state.joints, state.gripper, state.gripper_target,
             (it.mode.value, it.position, it.wxyz, it.since, it.grip, it.fall_from, it.rest_z)), events)


def _numbers(x) -> list[float]:
    if isinstance(x, (tuple, list)):
        return [v for e in x for v in _numbers(e)]
    return [float(x)] if isinstance(x, (int, float)) else []


def replay(w, traj: Trajectory, inputs) -> tuple[float, list]:
    """Seconds for all calls of one trajectory (fresh scene, static data built first), and the outputs.
    As on the server, each call gets the state that the previous call returned (unless the recording
    put the arm elsewhere in between)."""
    scene = w.build_scene(traj.complexity, traj.seed)
    w.collisions(inputs[0][0], scene)
    hold = w.hold_command
    out: list[Any] = []
    state = None
    t0 = time.perf_counter()
    for (recorded, command, duration), chained in zip(inputs, traj.chained, strict=False):
        result = hold(state if chained and out else recorded, scene, command, duration)
        state = result[0]
        out.append(result)
    return time.perf_counter() - t0, out


def compare(trajectories, worlds, inputs) -> list[str]:
    problems = []
    for i, traj in enumerate(trajectories):
        results = [[plain(*r) for r in replay(w, traj, inputs[w.name][i])[1]] for w in worlds]
        for k, (a, b) in enumerate(zip(*results, strict=False)):
            if a != b or repr(a) != repr(b):  # (repr: also the sign of zeros and the types of numbers)
                if a[1] != b[1] or a[0][5][0] != b[0][5][0]:
                    diff = math.inf
                else:
                    diff = max((abs(x - y) for x, y in zip(_numbers(a[0]), _numbers(b[0]), strict=False)),
                               default=math.inf)
                problems.append(f"{traj.kind}/{traj.complexity}/{traj.seed} call {k}: differ by {diff:.3g}: "
                                f"{a} != {b}")
                break
    return problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rev", help="also time experiment/world of this git revision and compare results")
    parser.add_argument("--seeds", type=int, default=3, help="scenes per complexity")
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    current = load_world(None)
    worlds = [current] + ([load_world(args.rev)] if args.rev else [])
    t0 = time.perf_counter()
    trajectories = record_all(current, args.seeds)
    n_sub = [sum(substeps(d, current.HOLD_SUBSTEP) for _, _, d in t.calls) for t in trajectories]
    print(f"recorded {len(trajectories)} trajectories, {sum(len(t.calls) for t in trajectories)} calls, "
          f"{sum(n_sub)} substeps in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    inputs = {w.name: [[(*convert(w, s, c), d) for s, c, d in t.calls] for t in trajectories] for w in worlds}

    problems = compare(trajectories, worlds, inputs) if len(worlds) > 1 else []
    for p in problems:
        print("DIFFERENT:", p[:2000], file=sys.stderr)

    groups = sorted({(t.kind, t.complexity) for t in trajectories}, key=lambda g: (KINDS.index(g[0]), g[1]))
    times: dict[str, dict[tuple[str, str], list[float]]] = {w.name: {g: [] for g in groups} for w in worlds}
    for _ in range(args.repeat):
        sums = {w.name: {g: 0.0 for g in groups} for w in worlds}
        for i, traj in enumerate(trajectories):
            for w in (worlds if _ % 2 == 0 else worlds[::-1]):
                sums[w.name][(traj.kind, traj.complexity)] += replay(w, traj, inputs[w.name][i])[0]
        for w in worlds:
            for g in groups:
                n = sum(n_sub[i] for i, t in enumerate(trajectories) if (t.kind, t.complexity) == g)
                times[w.name][g].append(sums[w.name][g] / n * 1e6)
    blocked = {g: sum(t.blocked for t in trajectories if (t.kind, t.complexity) == g) for g in groups}
    rows: list[dict[str, Any]] = []
    for g in groups:
        n = sum(n_sub[i] for i, t in enumerate(trajectories) if (t.kind, t.complexity) == g)
        row = {"kind": g[0], "complexity": g[1], "substeps": n, "blocked_calls": blocked[g]}
        for w in worlds:
            row[w.name] = statistics.median(times[w.name][g])
        rows.append(row)
    append_result("bench_physics.py", {"rev": args.rev, "seeds": args.seeds, "repeat": args.repeat},
                  {"rows": rows, "equal": not problems})
    if args.json:
        print(json.dumps({"rows": rows, "equal": not problems, "repeat": args.repeat}, indent=1))
    else:
        names = [w.name for w in worlds]
        print(f"{'kind':6s} {'cplx':5s} {'substeps':>8s} {'blocked':>7s} " +
              " ".join(f"{n[:12]:>12s}" for n in names) + ("   speed-up" if len(names) > 1 else ""))
        for r in rows:
            line = f"{r['kind']:6s} {r['complexity']:5s} {r['substeps']:8d} {r['blocked_calls']:7d} " + \
                " ".join(f"{r[n]:9.1f} us" for n in names)
            if len(names) > 1:
                line += f"   {r[names[1]] / r[names[0]]:6.2f}x"
            print(line)
        if len(names) > 1:
            total = {n: sum(r[n] * r["substeps"] for r in rows) / sum(r["substeps"] for r in rows) for n in names}
            print("all    (per substep, weighted) " + " ".join(f"{total[n]:9.1f} us" for n in names) +
                  f"   {total[names[1]] / total[names[0]]:6.2f}x")
            print("results: " + ("equal on every call (bit for bit)" if not problems else
                                 f"{len(problems)} trajectories differ"))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
