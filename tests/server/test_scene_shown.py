"""The decision window opens once the page shows the trial's scene (POST trials/shown), or at the wait limit."""

from datetime import timedelta

import pytest
from sqlalchemy import select

from experiment.world.trial import trial_scene
from server.models import Event, Participant, Trial, utcnow
from server.sweeper import sweep
from tests.server.factories import fast_config, join, make_client, make_study
from tests.server.test_admin_participants import participants

PRACTICE_1 = {"practice": True, "block": 0, "trial": 1}  # the demo's first practice trial: the robot tries itself
_FAST = fast_config()
#: The robot fast, the window long enough for a test's requests (the scene wait as by default).
CONFIG = _FAST.model_copy(update={"timing": _FAST.timing.model_copy(update={"decision_window_s": 30.0})})
WINDOW_S, WAIT_S = CONFIG.timing.decision_window_s, CONFIG.timing.scene_wait_s


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=CONFIG)
    return client


def post(client, token, what, body=None):
    return client.post(f"/api/p/{token}/{what}", json=body)


def at_first_practice_trial(client):
    token = join(client)["token"]
    post(client, token, "consent", {"agree": True})
    post(client, token, "instructions/done")
    state = post(client, token, "trials/start", PRACTICE_1).json()
    assert state["trial"]["robot_action"] == "auto"
    return token, state


def row(client) -> Trial:
    with client.app.state.services.sessionmaker() as session:
        return session.scalar(select(Trial))


def stamp_of(client) -> str:
    """The stamp of the current trial's scene, as the state tells the page."""
    with client.app.state.services.sessionmaker() as session:
        token_trial = session.scalar(select(Trial))
        public_id = session.scalar(select(Participant.public_id))
    return trial_scene(CONFIG.seed, public_id, token_trial.block_name, token_trial.trial, token_trial.complexity).stamp


def events(client, kind):
    with client.app.state.services.sessionmaker() as session:
        return [e.payload for e in session.scalars(select(Event).where(Event.kind == kind).order_by(Event.id))]


def test_the_window_opens_when_the_page_reports_the_scene_and_once_only(api):
    client = api
    token, started = at_first_practice_trial(client)
    trial = started["trial"]
    assert trial["stage"] == "presenting" and trial["decision_ms_left"] is None
    assert 0 < trial["scene_wait_ms_left"] <= WAIT_S * 1000
    refused = post(client, token, "trials/intervene", PRACTICE_1)  # no window yet: nothing to intervene in
    assert refused.status_code == 409 and "has not opened yet" in refused.json()["detail"]
    reloaded = client.get(f"/api/p/{token}/state").json()  # a reload while presenting: still presenting
    assert reloaded["trial"]["stage"] == "presenting" and row(client).window_opened_at is None

    stamp = trial["scene_stamp"]
    opened = post(client, token, "trials/shown",
                  PRACTICE_1 | {"view": "2d", "client_time_ms": 1234.5, "scene_stamp": stamp}).json()
    assert opened["trial"]["stage"] == "decision" and opened["trial"]["scene_wait_ms_left"] is None
    assert 0 < opened["trial"]["decision_ms_left"] <= WINDOW_S * 1000
    first = row(client)
    assert first.window_opened_by == "2d" and first.scene_shown_at == first.window_opened_at
    assert (first.scene_shown_view, first.scene_shown_client_ms) == ("2d", 1234.5)
    assert first.decision_deadline_at == first.window_opened_at + timedelta(seconds=WINDOW_S)

    again = post(client, token, "trials/shown", PRACTICE_1 | {"view": "3d", "scene_stamp": stamp})  # another tab
    assert again.status_code == 200 and again.json()["trial"]["stage"] == "decision"
    later = row(client)
    assert (later.decision_deadline_at, later.scene_shown_at, later.window_opened_by) == (
        first.decision_deadline_at, first.scene_shown_at, "2d")
    assert events(client, "decision_window_opened") == [{"practice": True, "block": 0, "trial": 1, "by": "2d"}]
    assert [e["view"] for e in events(client, "scene_shown")] == ["2d"]
    reloaded = client.get(f"/api/p/{token}/state").json()  # a reload during the window: what is left of it
    assert reloaded["trial"]["stage"] == "decision"
    assert reloaded["trial"]["decision_ms_left"] <= opened["trial"]["decision_ms_left"]

    pressed = post(client, token, "trials/intervene", PRACTICE_1 | {"window_opened_ms": 5000.0, "pressed_ms": 5750.0})
    assert pressed.json()["trial"]["stage"] == "teleop" and row(client).decision_time_ms == 750.0
    other = post(client, token, "trials/shown", PRACTICE_1 | {"practice": False, "block": 1})
    assert other.status_code == 422  # no view named
    wrong = post(client, token, "trials/shown", PRACTICE_1 | {"trial": 2, "view": "2d"})
    assert wrong.status_code == 409 and "not the current trial" in wrong.json()["detail"]


def test_without_a_report_the_window_opens_at_the_wait_limit_and_says_so(api):
    client = api
    token, _ = at_first_practice_trial(client)
    deadline = row(client).scene_deadline_at
    assert deadline == row(client).started_at + timedelta(seconds=WAIT_S)
    # the sweeper applies it for a page that went quiet (requests apply it too: see the late report below)
    assert sweep(client.app.state.services.sessionmaker, client.app.state.services.runtimes,
                 client.app.state.services.hub,
                 now=deadline + timedelta(seconds=WINDOW_S / 2)) == 1
    opened = row(client)
    assert (opened.stage, opened.window_opened_by, opened.window_opened_at) == ("decision", "wait_limit", deadline)
    assert opened.decision_deadline_at == deadline + timedelta(seconds=WINDOW_S) and opened.scene_shown_at is None

    # the page reports after the window opened by itself
    with client.app.state.services.sessionmaker.begin() as session:
        trial = session.scalar(select(Trial))
        trial.scene_deadline_at -= timedelta(seconds=WAIT_S)
        trial.window_opened_at -= timedelta(seconds=WAIT_S)
        trial.decision_deadline_at = utcnow() + timedelta(seconds=WINDOW_S / 2)
    late = post(client, token, "trials/shown", PRACTICE_1 | {"view": "2d", "scene_stamp": stamp_of(client)}).json()
    assert late["trial"]["stage"] == "decision"
    reported = row(client)
    assert reported.window_opened_by == "wait_limit" and reported.scene_shown_at > reported.window_opened_at
    assert [e["by"] for e in events(client, "decision_window_opened")] == ["wait_limit"]


@pytest.mark.parametrize("view", ["3d", "2d"])
def test_a_report_counts_only_with_the_stamp_of_the_trials_scene(api, view):
    """A page proves which scene its frame was drawn from; a frame of another trial's scene (the previous one, still
    on screen in a slow view) or a report without proof leaves the trial presenting."""
    client = api
    token, started = at_first_practice_trial(client)
    trial = row(client)
    with client.app.state.services.sessionmaker() as session:
        public_id = session.scalar(select(Participant.public_id))

    def stamp_of_trial(n):
        return trial_scene(CONFIG.seed, public_id, trial.block_name, n, trial.complexity).stamp

    assert started["trial"]["scene_stamp"] == stamp_of_trial(trial.trial)

    def answer(body):
        return post(client, token, "trials/shown", PRACTICE_1 | {"view": view} | body).json()["trial"]["stage"]

    assert answer({}) == "presenting"  # no proof
    assert answer({"scene_stamp": stamp_of_trial(trial.trial + 1)}) == "presenting"  # another trial's scene
    assert answer({"scene_stamp": "0" * 16}) == "presenting"
    assert row(client).scene_shown_at is None and row(client).window_opened_at is None
    assert post(client, token, "trials/shown", PRACTICE_1 | {"view": view, "scene_stamp": "<x>"}).status_code == 422
    assert answer({"scene_stamp": stamp_of_trial(trial.trial), "client_time_ms": 99.5}) == "decision"
    shown = row(client)
    assert (shown.window_opened_by, shown.scene_shown_view, shown.scene_shown_client_ms) == (view, view, 99.5)


def test_the_scene_for_the_2d_view_is_the_trials(api):
    client = api
    token = join(client)["token"]
    assert client.get(f"/api/p/{token}/trials/scene").status_code == 409  # no trial yet
    post(client, token, "consent", {"agree": True})
    post(client, token, "instructions/done")
    post(client, token, "trials/start", PRACTICE_1)
    shown = client.get(f"/api/p/{token}/trials/scene").json()
    trial = row(client)
    with client.app.state.services.sessionmaker() as session:
        public_id = session.scalar(select(Participant.public_id))
    scene = trial_scene(CONFIG.seed, public_id, trial.block_name, trial.trial, trial.complexity)
    assert shown["scene"]["seed"] == str(scene.seed) and shown["scene"]["complexity"] == trial.complexity
    assert shown["world"]["item"]["mode"] == "on_shelf"
    assert shown["scene_stamp"] == scene.stamp == client.get(f"/api/p/{token}/state").json()["trial"]["scene_stamp"]


def test_a_window_opened_at_the_wait_limit_is_a_quality_flag_on_the_dashboard(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=CONFIG)
    at_first_practice_trial(client)
    deadline = row(client).scene_deadline_at
    sweep(client.app.state.services.sessionmaker, client.app.state.services.runtimes, client.app.state.services.hub,
          now=deadline + timedelta(seconds=1))
    assert row(client).window_opened_by == "wait_limit"
    [listed] = participants(client, admin).values()
    assert [f["code"] for f in listed["flags"]] == ["scene_not_proven"]
    assert "1 decision window(s) (0 scored)" in listed["flags"][0]["detail"]
