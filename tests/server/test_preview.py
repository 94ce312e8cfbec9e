"""Preview sessions: the experimenter goes through a study as a participant; the data never notice."""

from __future__ import annotations

import csv
import io
import json
import zipfile

import pytest

from experiment.flow import next_step
from experiment.iohmm import paper_params
from server.models import AdminAudit, Answer, Event, Participant, Trial
from tests.server.factories import add_simulated_participants, auth, fast_config, join, make_client, make_study

EXPORTS = ("trials.csv", "surveys.csv", "participants.csv", "events.csv")


@pytest.fixture
def client_admin(database_url):
    return make_client(database_url=database_url)


def preview(client, admin, slug="s1") -> dict:
    response = client.post(f"/api/admin/studies/{slug}/preview", headers=auth(admin))
    assert response.status_code == 201, response.text
    return response.json()


def run_to_practice(client, token: str) -> None:
    """Consent, instructions and one finished practice trial (rows in trials, events)."""
    for step, body in (("consent", {"agree": True}), ("instructions/done", None)):
        assert client.post(f"/api/p/{token}/{step}", json=body).status_code == 200, step
    started = client.post(f"/api/p/{token}/trials/start", json={"practice": True, "block": 0, "trial": 1})
    assert started.status_code == 200, started.text


def export(client, admin, name: str, **params) -> bytes:
    response = client.get(f"/api/admin/studies/s1/export/{name}", params=params, headers=auth(admin))
    assert response.status_code == 200, response.text
    return response.content


def test_a_preview_runs_in_a_draft_and_in_a_closed_study_and_is_marked(client_admin):
    client, admin = client_admin
    make_study(client, admin, status="draft")
    started = preview(client, admin)
    assert started["participant_url"].endswith(f"/p/{started['token']}")
    state = client.get(f"/api/p/{started['token']}/state")
    assert state.status_code == 200 and state.json()["phase"] == "consent"
    assert client.post("/api/studies/s1/join").json()["code"] == "study_not_open"  # the draft stays closed to people

    client.post("/api/admin/studies/s1/open", headers=auth(admin))
    client.post("/api/admin/studies/s1/close", headers=auth(admin))
    preview(client, admin)
    listed = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()
    assert [p["preview"] for p in listed] == [True, True]
    study = client.get("/api/admin/studies/s1", headers=auth(admin)).json()
    assert study["participants"] == {} and study["preview_sessions"] == 2


def test_a_preview_takes_no_place_under_the_cap(client_admin):
    client, admin = client_admin
    config = fast_config()
    config = config.model_copy(update={"recruitment": config.recruitment.model_copy(
        update={"max_active_participants": 1})})
    make_study(client, admin, config=config)
    preview(client, admin)
    preview(client, admin)  # past the cap: a preview is not admitted, it is the experimenter's
    assert join(client, "s1", PROLIFIC_PID="real")["created"] is True  # the one place is still free
    full = client.post("/api/studies/s1/join", params={"PROLIFIC_PID": "second"})
    assert full.status_code == 503 and full.json()["code"] == "study_full"


def test_previews_do_not_change_counterbalancing(client_admin):
    client, admin = client_admin
    make_study(client, admin)  # fast_config: two blocks, counterbalanced
    for _ in range(3):  # previews that all reach their first scored trial first
        token = preview(client, admin)["token"]
        _to_first_scored_trial(client, token)
    for pid in ("a", "b"):
        _to_first_scored_trial(client, join(client, "s1", PROLIFIC_PID=pid)["token"])
    people = {p["external_id"]: p for p in client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()}
    real = [people[pid]["block_order"] for pid in ("a", "b")]
    assert sorted(map(tuple, real)) == sorted([("trust_aware", "trust_agnostic"), ("trust_agnostic", "trust_aware")])
    with client.app.state.services.sessionmaker() as session:
        counts = [p.assignment["counts_before"] for p in session.query(Participant).filter(
            Participant.preview.is_(False)).order_by(Participant.id)]
    assert all(n == 0 for _, n in counts[0])  # the first real participant saw no one before them


def _to_first_scored_trial(client, token: str) -> None:
    """Move the session straight to its first scored trial with the step machine and start it (which assigns the
    block order), without playing the practice."""
    from server.models import utcnow
    from server.services import sessions, trials
    from server.services.studies import get_study

    app = client.app
    with app.state.services.sessionmaker.begin() as session:
        participant = sessions.participant_by_token(session, token)
        runtime = sessions.runtime_of(session, app.state.services.runtimes, participant)
        while participant.step.phase != "trial":
            participant.step = next_step(runtime.config, participant.step, participant.block_order)
        trials.start_trial(session, get_study(session, "s1"), participant, runtime, participant.step.trial_ref,
                           now=utcnow())


def test_a_study_with_previews_exports_exactly_what_it_would_without_them(client_admin, tmp_path):
    client, admin = client_admin
    make_study(client, admin)
    add_simulated_participants(client, "s1", n=3, model=paper_params())
    before = {name: export(client, admin, name) for name in EXPORTS}
    tokens = [preview(client, admin)["token"] for _ in range(2)]
    run_to_practice(client, tokens[0])
    after = {name: export(client, admin, name) for name in EXPORTS}
    assert after == before  # byte for byte: not a row, not a count differs

    with_previews = csv.DictReader(io.StringIO(export(client, admin, "participants.csv",
                                                      include_preview="true").decode()))
    marked = {row["participant_id"]: row["preview"] for row in with_previews}
    assert sorted(marked.values()) == ["0", "0", "0", "1", "1"]
    events = export(client, admin, "events.csv", include_preview="true").decode()
    assert events.count("\n") > before["events.csv"].decode().count("\n")
    zipped = client.get("/api/admin/studies/s1/export.zip", headers=auth(admin))
    with zipfile.ZipFile(io.BytesIO(zipped.content)) as archive:
        manifest = json.loads(archive.read("manifest.json"))
        assert archive.read("participants.csv") == before["participants.csv"]
    assert manifest["include_preview"] is False and manifest["files"]["participants.csv"]["rows"] == 3


def test_fits_leave_previews_out_unless_asked(client_admin):
    from server.services.fits import study_fit_data
    from server.services.studies import get_study

    client, admin = client_admin
    make_study(client, admin)
    add_simulated_participants(client, "s1", n=2, model=paper_params())
    with client.app.state.services.sessionmaker() as session:
        without = study_fit_data(session, get_study(session, "s1"))
    add_simulated_participants(client, "s1", n=1, model=paper_params(), prefix="Pprev-")
    with client.app.state.services.sessionmaker.begin() as session:
        session.query(Participant).filter(Participant.public_id == "Pprev-0000").update({"preview": True})
    with client.app.state.services.sessionmaker() as session:
        study = get_study(session, "s1")
        again, included = study_fit_data(session, study), study_fit_data(session, study, include_preview=True)
    assert again.data_hash == without.data_hash and again.participants == without.participants
    assert included.participants == [*without.participants, "Pprev-0000"] and included.data_hash != without.data_hash


def test_deleting_previews(client_admin):
    client, admin = client_admin
    make_study(client, admin)
    add_simulated_participants(client, "s1", n=1, model=paper_params())
    first, second, third = (preview(client, admin) for _ in range(3))
    run_to_practice(client, first["token"])
    url = f"/api/admin/studies/s1/participants/{first['public_id']}"
    assert client.delete(url, headers=auth(admin)).json() == {"deleted": 1}
    assert client.delete(url, headers=auth(admin)).json() == {"deleted": 0}  # a retry is fine
    assert client.get(f"/api/p/{first['token']}/state").status_code == 404
    unknown = client.delete("/api/admin/studies/s1/participants/Pnobody", headers=auth(admin))
    assert unknown.status_code == 404
    real = client.delete("/api/admin/studies/s1/participants/Psim1-0000", headers=auth(admin))
    assert real.status_code == 409 and "give the reason" in real.json()["detail"]  # a real one: only with a reason

    assert client.delete("/api/admin/studies/s1/previews", headers=auth(admin)).json() == {"deleted": 2}
    assert client.delete("/api/admin/studies/s1/previews", headers=auth(admin)).json() == {"deleted": 0}
    with client.app.state.services.sessionmaker() as session:
        assert [p.public_id for p in session.query(Participant)] == ["Psim1-0000"]
        kept = session.query(Participant).one().id
        for table in (Trial, Answer, Event):
            assert {r.participant_id for r in session.query(table)} <= {kept, None}
        deleted = [a.participant_public_id for a in session.query(AdminAudit).filter(
            AdminAudit.action == "participant.delete_preview").order_by(AdminAudit.id)]
    assert deleted == [first["public_id"], second["public_id"], third["public_id"]]


def test_the_report_leaves_previews_out_unless_asked_and_says_when_it_has_them(client_admin, tmp_path):
    from server.services.report import study_report

    client, admin = client_admin
    make_study(client, admin)
    add_simulated_participants(client, "s1", n=3, model=paper_params())
    add_simulated_participants(client, "s1", n=1, model=paper_params(), prefix="Pprev-")
    with client.app.state.services.sessionmaker.begin() as session:
        session.query(Participant).filter(Participant.public_id == "Pprev-0000").update({"preview": True})
    factory = client.app.state.services.sessionmaker
    without = study_report(factory, "s1", tmp_path / "without", restarts=1).key_figures()["flow"]
    assert without["flow"]["joined"] == 3 and "preview_sessions" not in without
    included = study_report(factory, "s1", tmp_path / "with", restarts=1, include_preview=True)
    assert included.key_figures()["flow"]["flow"]["joined"] == 4
    assert included.key_figures()["flow"]["preview_sessions"] == 1
    assert "includes 1 preview session" in included.inline_html() and "preview sessions included" in included.title
