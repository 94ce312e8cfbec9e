"""kill -9 of `trustlab serve` at seeded random moments of a bot run, again and again (SPEC §10, issue 6).

After every kill the database holds every trial result and every questionnaire page a bot saw acknowledged,
unchanged and exactly once, and passes SQLite's integrity check; the server restarts on the same database,
the bots resume their sessions with the same links, and after the last restart every bot finishes with
exactly the study's trials and answers.
"""

from __future__ import annotations

import json
import random
import time
from collections import Counter
from typing import Any

import httpx
import pytest
from sqlalchemy import create_engine, text

from experiment.templates import demo_fast
from server.harness.bots import Bot
from server.harness.client import BotStats
from server.harness.live import expected_records, free_port, kill_server, make_bots, run_all, start_server

N_BOTS = 3
N_KILLS = 5
SEED = 6
#: A kill comes this long (s, uniform, seeded) after the bots' count of acknowledged trials reaches the kill's
#: (seeded, random) mark: inside the next trial, its teleoperation or a questionnaire, wherever that falls.
KILL_JITTER_S = (0.0, 0.4)
#: Longest wait for a mark (a slow machine); the kill then comes anyway.
MARK_TIMEOUT_S = 60
#: A bot thread ends as soon as its connection breaks; this only bounds a hang.
BOT_EXIT_TIMEOUT_S = 30
FINISH_TIMEOUT_S = 300

TrialKey = tuple[str, bool, int, int]  # external id, practice, block, trial
PageKey = tuple[str, str, str]  # external id, context, questionnaire


class RecordingBot(Bot):
    """A bot that also remembers every questionnaire page the server acknowledged (a 200 to its answers)."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.answered: dict[tuple[str, str], dict[str, float]] = {}
        self._asked_context = ""

    def answers(self, state: dict[str, Any]) -> dict[str, Any]:
        self._asked_context = state["questionnaire"]["context"]
        return super().answers(state)

    def post(self, what: str, body: Any = None, key: bool = True) -> dict[str, Any]:
        state = super().post(what, body, key)
        if what == "answers":
            self.answered[(self._asked_context, body["questionnaire"])] = body["answers"]
        return state


class Acknowledged:
    """Everything the bots were told is stored, over all rounds; a record acknowledged twice must not change."""

    def __init__(self) -> None:
        self.trials: dict[TrialKey, str] = {}
        self.pages: dict[PageKey, dict[str, float]] = {}
        self.tokens: dict[str, str] = {}

    def add(self, bots: list[RecordingBot]) -> None:
        for bot in bots:
            assert bot.external_id is not None
            if bot.token:  # the bot got as far as its join
                assert self.tokens.setdefault(bot.external_id, bot.token) == bot.token, "a resumed bot got a new link"
            for (practice, block, trial), outcome in bot.acknowledged.items():
                key = (bot.external_id, practice, block, trial)
                assert self.trials.setdefault(key, outcome) == outcome, f"trial {key} acknowledged with two outcomes"
            for (context, questionnaire), answers in bot.answered.items():
                key = (bot.external_id, context, questionnaire)
                assert self.pages.setdefault(key, answers) == answers, f"page {key} acknowledged twice, differently"


def check_database(database_url: str, acknowledged: Acknowledged) -> dict[str, Any]:
    """Integrity, no duplicates, every acknowledged record present and unchanged; returns the rows per participant."""
    engine = create_engine(database_url)
    try:
        with engine.connect() as conn:
            if engine.dialect.name == "sqlite":
                assert conn.execute(text("PRAGMA integrity_check")).scalars().all() == ["ok"]
                assert conn.execute(text("PRAGMA foreign_key_check")).all() == []
            trials = conn.execute(text(
                "SELECT p.external_id, t.practice, t.block, t.trial, t.stage, t.outcome FROM trial t "
                "JOIN participant p ON p.id = t.participant_id")).all()
            answers = conn.execute(text(
                "SELECT p.external_id, a.context, a.questionnaire, a.item, a.value FROM answer a "
                "JOIN participant p ON p.id = a.participant_id")).all()
            participants = conn.execute(text("SELECT external_id, status, block_order FROM participant")).all()
    finally:
        engine.dispose()
    trial_keys = Counter((e, bool(p), b, t) for e, p, b, t, _, _ in trials)
    assert [k for k, n in trial_keys.items() if n > 1] == [], "a trial was stored twice"
    answer_keys = Counter((e, c, q, i) for e, c, q, i, _ in answers)
    assert [k for k, n in answer_keys.items() if n > 1] == [], "an answer was stored twice"
    stored_trials = {(e, bool(p), b, t): (stage, outcome) for e, p, b, t, stage, outcome in trials}
    for key, outcome in acknowledged.trials.items():
        assert stored_trials.get(key) == ("done", outcome), f"acknowledged trial {key} missing or changed"
    stored_pages: dict[PageKey, dict[str, float]] = {}
    for e, c, q, item, value in answers:
        stored_pages.setdefault((e, c, q), {})[item] = value
    for key, page in acknowledged.pages.items():
        assert stored_pages.get(key) == page, f"acknowledged questionnaire page {key} missing or changed"
    return {"trials": trials, "answers": answers, "participants": participants}


def wait_for_progress(acknowledged: Acknowledged, bots: list[RecordingBot], mark: int) -> None:
    """Until ``mark`` trials in all have been acknowledged to the bots (this round's and the earlier ones)."""
    deadline = time.monotonic() + MARK_TIMEOUT_S
    while time.monotonic() < deadline:
        now = {(bot.external_id, *key) for bot in bots for key in list(bot.acknowledged)}
        if len(now | acknowledged.trials.keys()) >= mark:
            return
        time.sleep(0.01)


@pytest.mark.slow
def test_repeated_sigkill_loses_and_duplicates_nothing_and_every_bot_finishes(database_url, tmp_path):
    rng = random.Random(SEED)
    practice, scored, _ = expected_records(demo_fast(), [block.name for block in demo_fast().blocks])
    marks = sorted(rng.sample(range(1, N_BOTS * (practice + scored - 1)), N_KILLS))  # spread over the whole run
    port = free_port()
    acknowledged = Acknowledged()
    with open(tmp_path / "server.log", "a+", encoding="utf-8") as log:
        server, admin = start_server(database_url, port, log)
        try:
            created = httpx.post(f"http://127.0.0.1:{port}/api/admin/studies",
                                 headers={"Authorization": f"Bearer {admin}"},
                                 json={"status": "open", "slug": "fast", "template": "demo-fast"}, timeout=30)
            assert created.status_code == 201, created.text
            for kill in range(N_KILLS):
                bots = make_bots(port, BotStats(), N_BOTS, prefix="kill", bot_class=RecordingBot)
                results, threads = run_all(bots)
                wait_for_progress(acknowledged, bots, marks[kill])
                time.sleep(rng.uniform(*KILL_JITTER_S))
                kill_server(server)
                for thread in threads:
                    thread.join(timeout=BOT_EXIT_TIMEOUT_S)
                    assert not thread.is_alive(), "a bot hung after the server died"
                for bot in bots:
                    bot.http.close()
                acknowledged.add(bots)
                check_database(database_url, acknowledged)
                print(f"kill {kill + 1} (mark {marks[kill]}): {len(acknowledged.trials)} trials and "
                      f"{len(acknowledged.pages)} questionnaire pages acknowledged so far, all stored once", flush=True)
                started = time.monotonic()
                server, _ = start_server(database_url, port, log)
                print(f"  restarted in {time.monotonic() - started:.1f} s", flush=True)
            assert len(acknowledged.trials) > N_BOTS, "the kills came before the bots got anywhere"

            stats = BotStats()
            bots = make_bots(port, stats, N_BOTS, prefix="kill", bot_class=RecordingBot)
            results, threads = run_all(bots)
            for thread in threads:
                thread.join(timeout=FINISH_TIMEOUT_S)
            for bot in bots:
                bot.http.close()
            assert results == [None] * N_BOTS and stats.completed == N_BOTS, results
            acknowledged.add(bots)
        finally:
            kill_server(server)
    rows = check_database(database_url, acknowledged)
    assert len(acknowledged.tokens) == N_BOTS
    assert sorted((e, s) for e, s, _ in rows["participants"]) == [(f"kill-{i}", "completed") for i in range(N_BOTS)]
    for external_id, _, block_order in rows["participants"]:
        order = json.loads(block_order) if isinstance(block_order, str) else block_order  # raw JSON text on SQLite
        practice, scored, answers = expected_records(demo_fast(), order)
        mine = [r for r in rows["trials"] if r[0] == external_id]
        assert all(stage == "done" for _, _, _, _, stage, _ in mine)
        assert (sum(bool(r[1]) for r in mine), sum(not r[1] for r in mine)) == (practice, scored)
        assert len([r for r in rows["answers"] if r[0] == external_id]) == answers
