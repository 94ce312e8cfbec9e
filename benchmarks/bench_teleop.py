"""Teleoperation by a human-like operator at 2, 5, 10 and 30 client messages a second, against the real server.

Run: ``python benchmarks/bench_teleop.py [--rates 2 5 10 30] [--modes loop timer] [--participants 4]
[--per-complexity 3] [--seed 0] [--idle 5] [--json]``.

A fresh ``trustlab serve`` (one process, SQLite) gets a study in which the robot always asks for help
(policy ``always_ask``; no practice, no questionnaires; real-time robot; the default teleoperation time
limit). For each mode and rate, ``--participants`` participants join over HTTP at once and each
teleoperates ``--per-complexity`` low and as many high complexity trials over the websocket
(``websockets``), one after the other.

Each participant is ``experiment.participants.person.HumanModel``: it sees only what the socket sends (the
hello's setup and the latest world message), reacts a few hundred milliseconds late with some noise,
and holds keys (on/off per axis, Shift for precise) rather than sending ideal velocities. Between the
person and the socket is a page (``ClientLoop``), in one of two modes:

- ``loop``: the page's one loop runs ``rate`` times a second: it shows the latest world message to the
  person, sends an input message when the held keys changed (or G was pressed) and a keep-alive at least
  every ``limits.keepalive_s`` while motion is held. At a low rate the person sees a jerky picture and
  their key changes go out up to one loop period late: a page whose main thread is starved.
- ``timer``: the page takes keys and redraws every 40 ms (as a page that is not starved), and its
  keep-alive timer sends one message per tick at ``rate`` while motion is held: only how many messages
  the page sends differs between rates.

Prints per mode, rate and complexity: teleoperations, success rate, completion time (hello to ``over``)
median / p90 / max, messages sent per teleoperation (all, inputs, keep-alives); per mode and rate the
server's CPU seconds (its process tree, from /proc) per teleoperating participant-second (and net of what
the idle server uses), and the benchmark's own CPU (near 100 % its clients ran late). Then the issue's
targets: medians agree across rates (within 10 % of the highest rate's median), median under 20 s, at
least 95 % within the default time limit.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from experiment.config import AlwaysAskSpec, BlockConfig, PracticeConfig, StudyConfig, TimingConfig
from experiment.participants.page import PAGE_FRAME_S, ClientLoop
from experiment.participants.person import HumanModel
from experiment.schedule import CountsSchedule

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_load import Server  # noqa: E402 -- after the sys.path edit that makes benchmarks/ importable
from benchmarks.results_log import append_result  # noqa: E402 -- after the sys.path edit that makes benchmarks/ importable

DEFAULT_LIMIT_S = TimingConfig().teleop_time_limit_s  # the default time limit (90 s)
TARGET_MEDIAN_S = 20.0
TARGET_WITHIN_LIMIT = 0.95
TARGET_MEDIAN_SPREAD = 0.10
STALL_S = 60.0  # a participant who waits this long for the server to move on is an error


def study_config(per_complexity: int) -> dict[str, Any]:
    config = StudyConfig(
        title="teleoperation benchmark", description="The robot always asks: every trial is a teleoperation.",
        blocks=[BlockConfig(name="teleop", label="Part 1", policy=AlwaysAskSpec(),
                            schedule=CountsSchedule(n_low=per_complexity, n_high=per_complexity))],
        counterbalance="none", shelf_size=200, shelf_questionnaire=None, practice=PracticeConfig(enabled=False),
        timing=TimingConfig(animation_speed=1.0, teleop_time_limit_s=DEFAULT_LIMIT_S))
    return config.model_dump(mode="json")


@dataclass
class Teleop:
    mode: str
    rate: float
    complexity: str
    success: bool
    seconds: float  # hello to over (or to the socket closing)
    inputs: int
    keepalives: int
    reason: str
    refused: int = 0  # acks with ok false
    where: str = ""  # what it was and where it ended (printed for a failure)


@dataclass
class RateRun:
    mode: str
    rate: float
    teleops: list[Teleop] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    cpu_s: float = 0.0
    seconds: float = 0.0
    client_cpu: float = 0.0  # the benchmark's own CPU (s/s): near 1, its clients ran late


def _next(due: float, period: float, now: float) -> float:
    """The next tick of a timer: one period on, or one period from now when it fell behind (a browser's timers do
    not fire the missed ticks in a burst)."""
    due += period
    return due if due > now else now + period


async def teleoperate(ws_url: str, mode: str, rate: float, seed: int, clock0: float) -> Teleop | None:
    """One teleoperation over the socket, by a person at a client sending ``rate`` times a second (``mode``)."""
    from websockets.asyncio.client import connect

    async with connect(ws_url, open_timeout=10, max_size=2**20) as ws:
        hello = json.loads(await ws.recv())
        setup = hello.get("teleop")
        if setup is None:
            return None
        start = time.monotonic()
        human = HumanModel(setup, seed)
        client = ClientLoop(human, float(setup["limits"]["keepalive_s"]))
        latest: dict[str, Any] = {"world": setup["world"], "guidance": setup["guidance"]}
        over: dict[str, Any] | None = None
        refused = 0

        async def receive() -> None:
            nonlocal latest, over, refused
            async for raw in ws:
                message = json.loads(raw)
                if message["type"] == "world":
                    latest = message
                elif message["type"] == "ack":
                    client.ack(message)
                    refused += not message["ok"]
                elif message["type"] == "over":
                    over = message
                    return

        receiver = asyncio.create_task(receive())
        period = 1.0 / rate
        next_tick = next_frame = time.monotonic()
        try:
            while over is None and not receiver.done():
                now = time.monotonic()
                if mode == "loop":  # one loop at the rate: picture, keys and keep-alives
                    messages = client.tick(now - clock0, latest)
                    next_tick = _next(next_tick, period, now)
                else:  # keys and picture every frame, keep-alives on a timer at the rate
                    messages = []
                    if now >= next_frame - 1e-4:
                        messages += client.tick(now - clock0, latest, keepalive=False)
                        next_frame = _next(next_frame, PAGE_FRAME_S, now)
                    if now >= next_tick - 1e-4:
                        messages += client.keepalive(now - clock0)
                        next_tick = _next(next_tick, period, now)
                for message in messages:
                    await ws.send(json.dumps(message))
                wake = next_tick if mode == "loop" else min(next_tick, next_frame)
                await asyncio.sleep(max(0.0, wake - time.monotonic()))
        finally:
            if not receiver.done():
                await asyncio.wait([receiver], timeout=2.0)
            receiver.cancel()
        seconds = time.monotonic() - start
        reason = over["reason"] if over else "closed"
        scene = setup["scene"]
        where = (f"scene {scene['complexity']} seed {scene['seed']} slot {scene['target_slot']}, person seed {seed}: "
                 f"{reason} after {seconds:.1f} s, last doing '{human.phase}', guidance {latest['guidance']['step']}, "
                 f"item {latest['world']['item']['mode']}, tcp {latest['world']['tcp']}")
        return Teleop(mode, rate, scene["complexity"], reason == "deposited", seconds, client.inputs,
                      client.keepalives, reason, refused, where)


async def participant(url: str, slug: str, index: int, seed: int, run: RateRun) -> None:
    """Join, consent, read the instructions, then start and teleoperate every trial."""
    ws_base = "ws" + url[4:]
    clock0 = time.monotonic()
    async with httpx.AsyncClient(base_url=url, timeout=30) as http:
        async def post(path: str, body: Any = None) -> dict[str, Any]:
            response = await http.post(path, json=body)
            response.raise_for_status()
            return response.json()

        joined = await post(f"/api/studies/{slug}/join",
                            {"params": {"PROLIFIC_PID": f"bench-{run.mode}-{run.rate:g}-{seed}-{index}"}})
        token, state = joined["token"], joined["state"]
        stalled_at, teleops = time.monotonic(), 0
        while state["phase"] not in ("debrief", "declined"):
            if time.monotonic() - stalled_at > STALL_S or state["phase"] in ("abandoned", "withdrawn"):
                raise RuntimeError(f"stalled at {state['phase']} {state['step']}")
            phase = state["phase"]
            if phase == "consent":
                state = await post(f"/api/p/{token}/consent", {"agree": True})
            elif phase == "instructions":
                state = await post(f"/api/p/{token}/instructions/done")
            elif phase == "practice_done":
                state = await post(f"/api/p/{token}/practice/done")
            elif state.get("ready_to_start"):
                state = await post(f"/api/p/{token}/trials/start", state["ready_to_start"])
            elif (state.get("trial") or {}).get("stage") == "presenting":  # no view here: report text at once
                trial = state["trial"]
                state = await post(f"/api/p/{token}/trials/shown", {
                    "practice": trial["practice"], "block": trial["block"], "trial": trial["trial"], "view": "text"})
            elif (state.get("trial") or {}).get("stage") == "teleop":
                teleops += 1
                done = await teleoperate(f"{ws_base}/api/p/{token}/teleop", run.mode, run.rate,
                                         seed * 1_000_003 + index * 1009 + teleops, clock0)
                if done is not None:
                    run.teleops.append(done)
                    stalled_at = time.monotonic()
                state = (await http.get(f"/api/p/{token}/state")).json()
            else:
                await asyncio.sleep(0.2)
                state = (await http.get(f"/api/p/{token}/state")).json()


async def run_rate(server: Server, slug: str, mode: str, rate: float, participants: int, seed: int) -> RateRun:
    run = RateRun(mode, rate)
    cpu0, t0, own0 = server.cpu_seconds(), time.monotonic(), time.process_time()

    async def one(index: int) -> None:
        try:
            await participant(server.url, slug, index, seed, run)
        except Exception as exc:  # noqa: BLE001 -- a participant's failure is data for the table
            run.errors.append(f"participant {index}: {type(exc).__name__}: {exc}")

    await asyncio.gather(*(one(i) for i in range(participants)))
    run.seconds = time.monotonic() - t0
    run.client_cpu = (time.process_time() - own0) / run.seconds
    cpu1 = server.cpu_seconds()
    run.cpu_s = sum(used - cpu0.get(pid, 0.0) for pid, used in cpu1.items())
    return run


def _row(run: RateRun, complexity: str) -> tuple[str, dict[str, float]]:
    teleops = [t for t in run.teleops if t.complexity == complexity]
    head = f"{run.mode:<6}{run.rate:>5g}  {complexity:<5}"
    if not teleops:
        return head + f"{'(none)':>6}", {}
    seconds = np.array([t.seconds for t in teleops])
    ok = np.array([t.success for t in teleops])
    within = np.array([t.success and t.seconds <= DEFAULT_LIMIT_S for t in teleops])
    stats = {"n": len(teleops), "success": float(ok.mean()), "within_limit": float(within.mean()),
             "median_s": float(np.median(seconds)), "p90_s": float(np.percentile(seconds, 90)),
             "max_s": float(seconds.max()), "messages": float(np.mean([t.inputs + t.keepalives for t in teleops])),
             "inputs": float(np.mean([t.inputs for t in teleops])),
             "keepalives": float(np.mean([t.keepalives for t in teleops])),
             "refused": int(sum(t.refused for t in teleops))}
    line = (head + f"{stats['n']:>4}{100 * stats['success']:>8.0f}%"
            f"{stats['median_s']:>8.1f}{stats['p90_s']:>7.1f}{stats['max_s']:>7.1f}"
            f"{stats['messages']:>7.0f}{stats['inputs']:>7.0f}{stats['keepalives']:>6.0f}")
    return line, stats


async def main_async(args: argparse.Namespace) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(f"sqlite:///{Path(tmp) / 'bench-teleop.db'}")
        try:
            cpu0, t0 = server.cpu_seconds(), time.monotonic()
            await asyncio.sleep(args.idle)
            idle = (sum(server.cpu_seconds().values()) - sum(cpu0.values())) / (time.monotonic() - t0)
            print(f"Teleoperation: {args.participants} participants at once per rate, {args.per_complexity} low + "
                  f"{args.per_complexity} high teleoperations each; time limit {DEFAULT_LIMIT_S:.0f} s; "
                  f"{os.cpu_count()} CPUs; the idle server uses {idle:.3f} CPU s/s", flush=True)
            print("mode loop: the page's one loop runs at the rate (picture, keys, keep-alives: a starved page); "
                  "mode timer: keys and picture every frame, a keep-alive per tick of a timer at the rate", flush=True)
            print(f"{'mode':<6}{'rate':>5}  {'cplx':<5}{'n':>4}{'success':>9}{'median':>8}{'p90':>7}{'max':>7}"
                  f"{'msgs':>7}{'inputs':>7}{'keep':>6}   server CPU s per teleop-s (net of idle)", flush=True)
            for mode in args.modes:
                for rate in args.rates:
                    slug = f"teleop-{mode}-{str(rate).replace('.', '-')}"
                    response = httpx.post(server.url + "/api/admin/studies",
                                          json={"status": "open", "slug": slug,
                                                "config": study_config(args.per_complexity)},
                                          headers={"Authorization": f"Bearer {server.token}"}, timeout=30)
                    response.raise_for_status()
                    run = await run_rate(server, slug, mode, rate, args.participants, args.seed)
                    teleop_s = sum(t.seconds for t in run.teleops)
                    cpu_per = run.cpu_s / teleop_s if teleop_s else float("nan")
                    net = (run.cpu_s - idle * run.seconds) / teleop_s if teleop_s else float("nan")
                    for complexity in ("low", "high"):
                        line, stats = _row(run, complexity)
                        print(line + (f"   {cpu_per:.4f} ({net:.4f}; {run.cpu_s:.1f} CPU s, {teleop_s:.0f} "
                                      f"teleop-s in {run.seconds:.0f} s; clients {100 * run.client_cpu:.0f} % CPU)"
                                      if complexity == "low" else ""), flush=True)
                        if stats:
                            out.append({"mode": mode, "rate": rate, "complexity": complexity, **stats,
                                        "cpu_per_teleop_s": cpu_per, "net_cpu_per_teleop_s": net})
                    for error in run.errors[:5]:
                        print(f"    {error}", flush=True)
                    for failed in [t for t in run.teleops if not t.success][:5]:
                        print(f"    failed: {failed.where}", flush=True)
                    refusals = sum(t.refused for t in run.teleops)
                    if refusals:
                        print(f"    {refusals} messages refused by the server", flush=True)
        finally:
            server.stop()
    return out


def verdict(rows: list[dict[str, Any]]) -> list[str]:
    """The issue's targets per mode, rate and complexity (medians compared with the highest rate's)."""
    lines = []
    for mode in dict.fromkeys(r["mode"] for r in rows):
        for complexity in ("low", "high"):
            mine = {r["rate"]: r for r in rows if r["complexity"] == complexity and r["mode"] == mode}
            if not mine:
                continue
            reference = mine[max(mine)]
            for rate, r in sorted(mine.items()):
                spread = r["median_s"] / reference["median_s"] - 1
                checks = [(f"median vs {max(mine):g}/s", abs(spread) <= TARGET_MEDIAN_SPREAD, f"{100 * spread:+.0f} %"),
                          ("median", r["median_s"] < TARGET_MEDIAN_S, f"{r['median_s']:.1f} s"),
                          ("within the limit", r["within_limit"] >= TARGET_WITHIN_LIMIT,
                           f"{100 * r['within_limit']:.0f} %")]
                failed = [f"{name} {value}" for name, ok, value in checks if not ok]
                lines.append(f"  {'PASS' if not failed else 'FAIL'}: {mode} {complexity} at {rate:g}/s: "
                             + ", ".join(f"{name} {value}" for name, ok, value in checks if ok)
                             + ("; NOT MET: " + ", ".join(failed) if failed else ""))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[2.0, 5.0, 10.0, 30.0])
    parser.add_argument("--modes", nargs="+", choices=["loop", "timer"], default=["loop", "timer"])
    parser.add_argument("--idle", type=float, default=5.0, help="seconds to measure the idle server's CPU first")
    parser.add_argument("--participants", type=int, default=4, help="participants teleoperating at once per rate")
    parser.add_argument("--per-complexity", type=int, default=3, help="low (and high) teleoperations per participant")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print one JSON line per rate and complexity as well")
    args = parser.parse_args()
    rows = asyncio.run(main_async(args))
    print(f"Targets (issue 13): medians within {100 * TARGET_MEDIAN_SPREAD:.0f} % across rates, median < "
          f"{TARGET_MEDIAN_S:.0f} s, >= {100 * TARGET_WITHIN_LIMIT:.0f} % within {DEFAULT_LIMIT_S:.0f} s")
    for line in verdict(rows):
        print(line)
    append_result("bench_teleop.py", {"rates": args.rates, "modes": args.modes, "participants": args.participants,
                                      "per_complexity": args.per_complexity, "seed": args.seed},
                  {"rows": rows, "verdict": verdict(rows)})
    if args.json:
        for row in rows:
            print(json.dumps(row))


if __name__ == "__main__":
    main()
