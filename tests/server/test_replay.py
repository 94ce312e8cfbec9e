"""Replays from the database alone (issue 39): a bot's run of every kind of trial, rebuilt to its recorded outcomes;
a teleoperation log cut short said to be missing; the replay file from the CLI and the admin API."""

from __future__ import annotations

import base64
import json
import re
import shutil
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import msgspec
import pytest
import zstandard
from fastapi.testclient import TestClient
from sqlalchemy import select
from typer.testing import CliRunner

from experiment.config import AlwaysAutoSpec, BlockConfig, PracticeConfig, PracticeTrial, StudyConfig, TimingConfig
from experiment.iohmm import paper_params
from experiment.replay import reconstruct, resting_state
from experiment.schedule import CountsSchedule
from experiment.task import Complexity, RobotAction, TaskParams
from experiment.world.trial import trial_scene
from server.cli import app as cli
from server.harness.crowd import run_bots
from server.models import Event, Participant
from server.services.replay import load_trials
from server.viewer.recording import record
from server.viewer.scene import start_state, static_nodes
from tests.server.factories import auth, make_client, make_study


def every_kind() -> StudyConfig:
    """Practice trials a bot takes as hinted: relied on (low: the robot succeeds; high: it fails), taken over, and
    the robot asking (a teleoperation); then one scored trial. Sped up 20x (teleoperation 8x, the cap)."""
    return StudyConfig(
        title="replay of every kind", counterbalance="none", shelf_size=2,
        practice=PracticeConfig(trials=[
            PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.AUTO, human_action_hint="rely"),
            PracticeTrial(complexity=Complexity.HIGH, robot_action=RobotAction.AUTO, human_action_hint="rely"),
            PracticeTrial(complexity=Complexity.LOW, robot_action=RobotAction.AUTO, human_action_hint="intervene"),
            PracticeTrial(complexity=Complexity.HIGH, robot_action=RobotAction.ASK)]),
        blocks=[BlockConfig(name="auto", policy=AlwaysAutoSpec(), schedule=CountsSchedule(n_low=1, n_high=0))],
        task=TaskParams(p_success_low=1.0, p_success_high=0.0),
        timing=TimingConfig(decision_window_s=0.2, animation_speed=20.0))


@dataclass(frozen=True)
class Ran:
    client: TestClient
    admin: str
    database_url: str
    public_id: str


@pytest.fixture(scope="module")
def ran(sqlite_template: Path, tmp_path_factory: pytest.TempPathFactory) -> Ran:
    """One bot through the study (scripted teleoperation), in process."""
    path = tmp_path_factory.mktemp("replay") / "replay.db"
    shutil.copy(sqlite_template, path)
    url = f"sqlite:///{path}"
    client, admin = make_client(database_url=url)
    make_study(client, admin, config=every_kind())
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(), participants=1)
    assert summary.errors == [] and summary.completed == 1
    with client.app.state.services.sessionmaker() as session:
        public_id = session.scalars(select(Participant.public_id)).one()
    return Ran(client, admin, url, public_id)


def test_every_kind_of_trial_is_rebuilt_to_its_recorded_outcome(ran):
    with ran.client.app.state.services.sessionmaker() as session:
        loaded = load_trials(session, "s1", ran.public_id)
    kinds = set()
    for trial in loaded.trials:
        replay = reconstruct(trial.record)
        assert replay.reproduced, (trial.label, replay.missing)
        assert replay.reconstructed == replay.recorded
        row = trial.record
        # (a failure's mode, collision or drop, is drawn from the participant's random id: either is the kind)
        kinds.add((row.robot_action.value, row.human_action.value if row.human_action else None,
                   "teleop" if replay.parts else replay.recorded.replace("(drop)", "(collision or drop)")
                   .replace("(collision)", "(collision or drop)")))
        if replay.parts:  # the re-simulation met the logged grasp and deposit, at the logged times
            assert [e for _, e in replay.parts[-1].resim.events] == ["grasped", "deposited"]
    assert kinds == {("auto", "rely", "the robot put the item in the bin"), ("auto", "rely", "the robot failed "
                     "(collision or drop)"), ("auto", "intervene", "teleop"), ("ask", "intervene", "teleop")}


def test_a_teleoperation_log_cut_short_says_what_is_missing(ran):
    """As after a kill -9: the entries of the teleoperation's last second were never written."""
    services = ran.client.app.state.services
    with services.sessionmaker() as session:
        logs = session.scalars(select(Event).where(Event.kind == "teleop_log").order_by(Event.id)).all()
        last = [e for e in logs if e.payload["trial"] == 3][-1]  # practice trial 3: the intervention
        entries = [e for log in logs if log.payload["trial"] == 3 for e in log.payload["entries"]]
        end_ms = entries[-1]["server_ms"]
        kept = [e for e in last.payload["entries"] if e["server_ms"] < end_ms - 300]
        last.payload = {**last.payload, "entries": kept}
        if not kept:
            session.delete(last)
        session.flush()
        loaded = load_trials(session, "s1", ran.public_id, [next(t.ref for t in load_trials(
            session, "s1", ran.public_id).trials if t.ref.practice and t.ref.trial == 3)])
        session.rollback()
    replay = reconstruct(loaded.trials[0].record)
    assert not replay.reproduced
    assert replay.missing[0].startswith("the input log ends at") and "before the recorded deposit" in replay.missing[0]
    assert "deposited" not in [m.kind for m in replay.moments] and "missing" in [m.kind for m in replay.moments]


def test_the_replay_looks_like_the_participants_view(ran):
    """The recording holds the live view's scene nodes, the robot at rest where the trial starts, the clock for the
    page's timeline, and lasts as long as the trial's timeline."""
    with ran.client.app.state.services.sessionmaker() as session:
        trial = load_trials(session, "s1", ran.public_id).trials[1]
    replay = reconstruct(trial.record)
    assert resting_state(replay.scene) == start_state(replay.scene)  # experiment/ has its own copy of the rest pose
    data = zstandard.ZstdDecompressor().decompress(record(replay)[8:])
    payload = msgspec.msgpack.decode(data[8:8 + int.from_bytes(data[:8], "little")])
    assert payload["durationSeconds"] == pytest.approx(replay.duration)
    names = {m.get("name") for _, m in payload["messages"]}
    assert set(static_nodes(trial_scene(trial.record.study_seed, ran.public_id, "practice", 2, "high")).names) <= names
    assert {"/obstacles/0", "/items/target/geom"} <= names
    clocks = [t for t, m in payload["messages"] if m["type"] == "RunJavascriptMessage"]
    assert clocks[0] == 0 and clocks[-1] == pytest.approx(replay.duration) and len(clocks) > 10 * replay.duration


def page_data(html: str) -> dict:
    found = re.search(r'<script id="replay-data" type="application/json">(.*?)</script>', html, re.S)
    assert found
    return json.loads(found.group(1))


def test_the_cli_writes_a_participant_as_one_file_and_trials_as_files_of_their_own(ran, tmp_path):
    runner = CliRunner()
    result = runner.invoke(cli, ["replay", "s1", "--participant", ran.public_id, "--out", str(tmp_path / "all"),
                                 "--database-url", ran.database_url])
    assert result.exit_code == 0, result.output
    assert "[5/5] block 1 (auto), trial 1: reconstructed" in result.output
    assert result.output.count("reproduced") == 5
    bundle = (tmp_path / "all" / f"replay-{ran.public_id}.html").read_text(encoding="utf-8")
    data = page_data(bundle)
    assert [t["label"] for t in data["trials"]][0] == "practice trial 1" and len(data["trials"]) == 5
    assert all(t["reproduced"] and base64.b64decode(t["recording"]) for t in data["trials"])
    assert bundle.count("window.__VISER_EMBED_DATA__") == 1  # viser's client once, the trials' recordings beside it
    result = runner.invoke(cli, ["replay", "s1", "--participant", ran.public_id, "--trial", "1:0:3", "--trial",
                                 "0:1:1", "--out", str(tmp_path / "two"), "--database-url", ran.database_url])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == [f"replay-{ran.public_id}-block1-trial1.html",
                                                                   f"replay-{ran.public_id}-practice-3.html"]
    result = runner.invoke(cli, ["replay", "s1", "--participant", ran.public_id, "--trial", "0:9:9", "--out",
                                 str(tmp_path / "none"), "--database-url", ran.database_url])
    assert result.exit_code == 2 and "has no trial 9 of block 9" in result.output


def test_the_admin_api_sends_the_replay_file(ran):
    path = f"/api/admin/studies/s1/participants/{ran.public_id}/replay"
    response = ran.client.get(path, params={"trial": "practice:0:2"}, headers=auth(ran.admin))
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/html")
    assert response.headers["content-disposition"] == f'attachment; filename="replay-{ran.public_id}-practice-2.html"'
    [recorded] = [t["recorded"] for t in page_data(response.text)["trials"]]
    assert recorded in ("the robot failed (collision)", "the robot failed (drop)")  # drawn from the random id
    assert ran.client.get(path).status_code == 401
    assert ran.client.get(path, params={"trial": "2:1"}, headers=auth(ran.admin)).status_code == 422
    assert ran.client.get(path, params={"trial": "0:4:1"}, headers=auth(ran.admin)).status_code == 404
    assert ran.client.get("/api/admin/studies/s1/participants/Pnobody/replay",
                          headers=auth(ran.admin)).status_code == 404


def test_camera_changes_are_placed_on_the_trial_they_happened_in(ran):
    """Camera events name no trial: they belong to the trial that ran when they were written, and the last one before
    a trial is the preset it starts in."""
    from datetime import timedelta

    from server.models import Trial

    with ran.client.app.state.services.sessionmaker() as session:
        participant = session.scalars(select(Participant)).one()
        first, second = session.scalars(select(Trial).where(Trial.participant_id == participant.id)
                                        .order_by(Trial.id).limit(2)).all()
        for at, view in ((first.started_at + timedelta(seconds=0.1), "local"),
                         (second.started_at + timedelta(seconds=0.2), "end_effector")):
            session.add(Event(study_id=participant.study_id, participant_id=participant.id, kind="camera",
                              payload={"view": view, "viewers": 1}, server_monotonic_s=0.0, created_at=at))
        session.flush()
        loaded = load_trials(session, "s1", ran.public_id, [first.ref, second.ref])
        session.rollback()
    one, two = (t.record for t in loaded.trials)
    assert (one.initial_view, [c.view for c in one.camera]) == ("world", ["local"])
    assert (two.initial_view, [(round(c.t, 3), c.view) for c in two.camera]) == ("local", [(0.2, "end_effector")])
    assert reconstruct(two).view_at(0.3) == "end_effector"
