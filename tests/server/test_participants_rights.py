"""The participant's rights (issue 41): withdrawal (keep or delete), deletion on request, retention, pseudonymised
exports and the recruitment id kept out of URLs.

One app per backend for the module (each test makes studies of its own), so the module stays fast. The deletion
tests scan every table of the metadata for the deleted participant: a table added later is scanned too.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import zipfile
from collections.abc import Iterator
from datetime import UTC, date, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import inspect, select
from typer.testing import CliRunner

from experiment.events import EventKind
from experiment.privacy import PSEUDONYM_HEX, PrivacyConfig
from server.cli import app as cli
from server.db.engine import Base
from server.faults import FaultLog
from server.models import AdminAudit, Answer, Participant, Trial, utcnow
from server.services.audit import log_event
from server.services.sessions import hash_token
from server.sweeper import sweep, sweep_retention
from tests.conftest import BACKENDS, create_postgres_database, drop_postgres_database, postgres_database_url
from tests.server.factories import auth, fast_config, make_client, make_study

PARTICIPANT_FK = ("participant", "id")


@pytest.fixture(scope="module", params=BACKENDS)
def world(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, str, str]]:
    """(client, admin token, database URL): one migrated database and app for the module."""
    if request.param == "sqlite":
        path = tmp_path_factory.mktemp("rights") / "trustlab.db"
        shutil.copy(request.getfixturevalue("sqlite_template"), path)
        url = f"sqlite:///{path}"
        client, admin = make_client(database_url=url)
        yield client, admin, url
        return
    name = create_postgres_database(template=request.getfixturevalue("postgres_template"))
    try:
        url = postgres_database_url(name)
        client, admin = make_client(database_url=url)
        yield client, admin, url
    finally:
        drop_postgres_database(name)


def open_study(client, admin, slug: str, *, completion: dict[str, Any] | None = None, **privacy: Any) -> None:
    config = fast_config()
    update: dict[str, Any] = {"privacy": PrivacyConfig(**privacy)}
    if completion:
        update["completion"] = config.completion.model_copy(update=completion)
    make_study(client, admin, slug=slug, config=config.model_copy(update=update))


def join(client, slug: str, key: str, **params: str) -> dict[str, Any]:
    response = client.post(f"/api/studies/{slug}/join", json={"params": params, "resume_key": key})
    assert response.status_code == 200, response.text
    return response.json()


def withdraw(client, token: str) -> dict[str, Any]:
    response = client.post(f"/api/p/{token}/withdraw", json={"confirm": True})
    assert response.status_code == 200, response.text
    return response.json()


def factory(client):
    return client.app.state.services.sessionmaker


def participant_row(client, public_id: str) -> Participant | None:
    with factory(client).begin() as session:
        row = session.scalar(select(Participant).where(Participant.public_id == public_id))
        if row is not None:
            session.expunge(row)
        return row


def public_id_of(client, token: str) -> str:
    with factory(client).begin() as session:
        return session.scalar(select(Participant.public_id).where(Participant.token_hash == hash_token(token)))


def populate(client, admin, slug: str, pid: str) -> dict[str, Any]:
    """A participant with a row in every table that holds participants' data: trials, answers, events (a teleop log
    among them), a stored idempotent response, a questionnaire draft, audit lines about them. Returns what names
    them: token, public id, database id, external id, token hash, resume key hash."""
    key = f"key-{pid}-" + "x" * 16
    token = join(client, slug, key, PROLIFIC_PID=pid, SESSION_ID=f"sess-{pid}", STUDY_ID="prolific-study")["token"]
    base = f"/api/p/{token}"
    assert client.post(f"{base}/consent", json={"agree": True}, headers={"Idempotency-Key": f"c-{pid}"}).status_code \
        == 200
    assert client.post(f"{base}/instructions/done").status_code == 200
    assert client.post(f"{base}/trials/start", json={"practice": True, "block": 0, "trial": 1}).status_code == 200
    events = [{"kind": "window_focus", "client_time_ms": 1.0, "payload": {"note": pid}}]
    assert client.post(f"{base}/events", json={"events": events}).status_code == 200
    public_id = public_id_of(client, token)
    for action in ("exclude", "include"):
        assert client.post(f"/api/admin/studies/{slug}/participants/{public_id}/{action}",
                           json={"reason": "a note"}, headers=auth(admin)).status_code == 200
    with factory(client).begin() as session:
        participant = session.scalar(select(Participant).where(Participant.public_id == public_id))
        session.add(Answer(participant_id=participant.id, study_version_id=participant.study_version_id,
                           context="before", questionnaire="q", item="i1", value=3.0, text=f"answer of {pid}"))
        log_event(session, participant.study_id, participant.id, EventKind.TELEOP_LOG, practice=True, block=0,
                  trial=1, entries=[{"t": 0.1, "event": "move"}])
        participant.survey_draft = {"questionnaire": "q", "context": "before", "answers": {"i1": 2}}
        return {"token": token, "public_id": public_id, "id": participant.id, "external_id": pid,
                "token_hash": participant.token_hash, "resume_key_hash": participant.resume_key_hash}


def holders(client, who: dict[str, Any]) -> set[str]:
    """Every table.column of the metadata that still holds ``who``: a foreign key to their participant row, or any
    value (JSON included) containing their public id, external id, token, token hash or resume key hash."""
    needles = [who[k] for k in ("public_id", "external_id", "token", "token_hash", "resume_key_hash")]
    found = set()
    with factory(client)() as session:
        for table in Base.metadata.sorted_tables:
            keys = [c.name for c in table.columns
                    if any((fk.column.table.name, fk.column.name) == PARTICIPANT_FK for fk in c.foreign_keys)]
            for row in session.execute(select(table)).mappings():
                if table.name == "participant" and row["id"] == who["id"]:
                    found.add("participant.id")
                found |= {f"{table.name}.{k}" for k in keys if row[k] == who["id"]}
                for name, value in row.items():
                    text = json.dumps(value, default=str) if not isinstance(value, str) else value
                    if any(n in text for n in needles):
                        found.add(f"{table.name}.{name}")
    return found


def test_every_table_is_scanned(world):
    """The scan reads every table of the database: none exists outside the metadata (but Alembic's own)."""
    client, _, _ = world
    engine = factory(client).kw["bind"]
    assert set(inspect(engine).get_table_names()) - set(Base.metadata.tables) == {"alembic_version"}


def test_withdrawal_that_keeps_the_data(world):
    client, admin, _ = world
    open_study(client, admin, "keep", withdrawal="keep")
    who = populate(client, admin, "keep", "pid-keep")
    other = populate(client, admin, "keep", "pid-other")
    state = withdraw(client, who["token"])
    assert state["phase"] == "withdrawn" and state["status"] == "withdrawn"
    assert state["withdrawal"] == {"data": "keep", "text": None, "by": "participant"}
    assert state["completion"] is None  # no withdrawn code or redirect by default
    retried = withdraw(client, who["token"])  # idempotent: the same end again
    assert retried | {"server_time": None} == state | {"server_time": None}

    row = participant_row(client, who["public_id"])
    assert row.status == "withdrawn" and row.excluded and row.exclusion_reason == "withdrawn"
    assert (row.external_id, row.recruitment, row.resume_key_hash, row.survey_draft) == (None, {}, None, None)
    assert row.personal_data_erased_at is not None
    with factory(client)() as session:  # the research data stay
        assert session.scalar(select(Trial.id).where(Trial.participant_id == who["id"])) is not None
        kinds = session.scalars(select(AdminAudit.action).where(AdminAudit.participant_public_id == who["public_id"]))
        assert "participant.withdraw" in set(kinds)
    again = client.get(f"/api/p/{who['token']}/state").json()
    assert again["phase"] == "withdrawn" and again["withdrawal"]["by"] == "participant"
    assert client.post(f"/api/p/{who['token']}/instructions/done").status_code == 410
    assert participant_row(client, other["public_id"]).external_id == "pid-other"  # the other one untouched
    rows = {r["participant_id"]: r for r in csv_rows(client, admin, "keep", "participants.csv")}
    assert rows[who["public_id"]]["outcome"] == "withdrawn" and rows[who["public_id"]]["excluded"] == "1"
    assert rows[who["public_id"]]["personal_data_erased_at"] and rows[who["public_id"]]["external_id"] == ""
    assert {r["kind"] for r in csv_rows(client, admin, "keep", "events.csv")
            if r["participant_id"] == who["public_id"]} >= {"withdrawn", "teleop_log"}


def test_withdrawal_that_deletes_the_data_leaves_no_row(world):
    client, admin, _ = world
    open_study(client, admin, "del", withdrawal="delete", completion={
        "code_withdrawn": "RETURNED-1", "redirect_withdrawn": "https://r.example/return?cc={code}&p={external_id}"})
    who = populate(client, admin, "del", "pid-del")
    other = populate(client, admin, "del", "pid-stays")
    before = {name: csv_rows(client, admin, "del", name) for name in ("trials.csv", "surveys.csv", "events.csv")}
    assert holders(client, who) >= {"participant.id", "trial.participant_id", "answer.participant_id",
                                    "event.participant_id", "idempotent_response.participant_id",
                                    "admin_audit.participant_public_id"}  # the scan sees them before

    state = withdraw(client, who["token"])
    assert state["phase"] == "withdrawn" and state["withdrawal"] == {"data": "delete", "text": None,
                                                                     "by": "participant"}
    assert state["completion"]["code"] == "RETURNED-1"
    assert state["completion"]["redirect_url"] == "https://r.example/return?cc=RETURNED-1&p=pid-del"
    assert holders(client, who) == set()

    retried = withdraw(client, who["token"])  # a retry after the deletion: the same end, no external id left
    assert retried["phase"] == "withdrawn" and retried["withdrawal"]["by"] == "participant"
    assert retried["completion"]["redirect_url"] == "https://r.example/return?cc=RETURNED-1&p="
    assert client.get(f"/api/p/{who['token']}/state").json()["phase"] == "withdrawn"  # a reload shows the end
    assert client.get(f"/api/p/{'z' * 32}/state").status_code == 404  # an unknown link is still unknown

    with factory(client)() as session:
        line = session.scalars(select(AdminAudit).where(AdminAudit.action == "participant.delete")
                               .order_by(AdminAudit.id.desc())).first()
    assert line.participant_public_id is None and line.detail["by"] == "participant"
    assert line.detail["rows"]["trial"] >= 1 and line.detail["rows"]["event"] >= 3
    assert holders(client, who) == set()  # the retry and the reload left nothing either
    after = {name: csv_rows(client, admin, "del", name) for name in before}
    for name, rows in before.items():  # the other participant's data are exactly as they were
        assert [r for r in after[name] if r["participant_id"] == other["public_id"]] == \
            [r for r in rows if r["participant_id"] == other["public_id"]]
        assert not any(r["participant_id"] == who["public_id"] for r in after[name])
    services, faults = client.app.state.services, FaultLog()  # the sweep after a deletion mid-trial: no fault
    sweep(services.sessionmaker, services.runtimes, services.hub, now=utcnow() + timedelta(minutes=5), faults=faults)
    assert faults.recent() == [] and holders(client, who) == set()


def test_the_experimenter_deletes_on_request_with_a_reason(world):
    client, admin, _ = world
    open_study(client, admin, "ask")
    who = populate(client, admin, "ask", "pid-ask")
    duplicate = join(client, "ask", "another-browser-key-0000", PROLIFIC_PID="pid-ask")  # a second session, same id
    url = f"/api/admin/studies/ask/participants/{who['public_id']}"
    refused = client.request("DELETE", url, headers=auth(admin))
    assert refused.status_code == 409 and "reason" in refused.json()["detail"]
    assert client.request("DELETE", url, json={"reason": "asked by email"}, headers=auth(admin)).json() == \
        {"deleted": 1}
    assert client.request("DELETE", url, json={"reason": "asked by email"}, headers=auth(admin)).json() == \
        {"deleted": 0}  # a repeated request is fine
    assert client.request("DELETE", "/api/admin/studies/ask/participants/Pnobody", json={"reason": "x"},
                          headers=auth(admin)).status_code == 404
    assert holders(client, who | {"external_id": "no-such-value"}) == set()  # the duplicate keeps its own id
    dup = participant_row(client, public_id_of(client, duplicate["token"]))
    assert dup.duplicate_of.startswith("deleted-") and dup.external_id == "pid-ask"
    listed = client.get("/api/admin/studies/ask/participants", headers=auth(admin)).json()
    assert [p["public_id"] for p in listed] == [dup.public_id]
    assert "duplicate_id" in {f["code"] for f in listed[0]["flags"]}  # its flag stays
    study = client.get("/api/admin/studies/ask", headers=auth(admin)).json()
    assert study["personal_data"]["deleted_participants"] == 1
    with factory(client)() as session:
        line = session.scalars(select(AdminAudit).where(AdminAudit.action == "participant.delete")
                               .order_by(AdminAudit.id.desc())).first()
        unlinked = session.scalars(select(AdminAudit).where(AdminAudit.study_id == line.study_id,
                                                            AdminAudit.action == "participant.exclude")).all()
    assert line.detail["by"] == "admin" and line.detail["reason"] == "asked by email"
    assert [u.participant_public_id for u in unlinked] == [None]
    assert unlinked[0].detail["subject"] == line.detail["subject"]  # the history stays, naming no one
    gone = client.get(f"/api/p/{who['token']}/state").json()
    assert gone["phase"] == "withdrawn" and gone["withdrawal"]["by"] == "researcher"


def test_the_researchers_withdrawal_follows_the_study(world):
    client, admin, _ = world
    open_study(client, admin, "rw", withdrawal="delete")
    who = populate(client, admin, "rw", "pid-rw")
    response = client.post(f"/api/admin/studies/rw/participants/{who['public_id']}/withdraw",
                           json={"reason": "asked by phone"}, headers=auth(admin))
    assert response.status_code == 200, response.text
    assert holders(client, who) == set()
    assert client.get(f"/api/p/{who['token']}/state").json()["withdrawal"]["by"] == "researcher"


def test_exports_stay_valid_after_deletions(world):
    """Every export file of a study with deletions and a kept withdrawal reads against its codebook."""
    client, admin, _ = world
    open_study(client, admin, "exp", withdrawal="delete")
    gone, stays = populate(client, admin, "exp", "pid-x1"), populate(client, admin, "exp", "pid-x2")
    withdraw(client, gone["token"])
    archive = client.get("/api/admin/studies/exp/export.zip", headers=auth(admin))
    assert archive.status_code == 200
    with zipfile.ZipFile(io.BytesIO(archive.content)) as zipped:
        manifest = json.loads(zipped.read("manifest.json"))
        for name in ("trials.csv", "surveys.csv", "participants.csv", "events.csv"):
            rows = list(csv.DictReader(io.StringIO(zipped.read(name).decode())))
            assert len(rows) == manifest["files"][name]["rows"]
            assert {r["participant_id"] for r in rows} <= {stays["public_id"], ""}
    assert manifest["pseudonymised"] is False
    assert client.get("/api/admin/studies/exp/export/psych-ds.zip", headers=auth(admin)).status_code == 200


def csv_rows(client, admin, slug: str, name: str, **params: Any) -> list[dict[str, str]]:
    response = client.get(f"/api/admin/studies/{slug}/export/{name}", params=params, headers=auth(admin))
    assert response.status_code == 200, response.text
    return list(csv.DictReader(io.StringIO(response.content.decode())))


def test_retention_erases_personal_fields_and_only_them(world):
    client, admin, _ = world
    open_study(client, admin, "ret", erase_personal_after_days=30)
    open_study(client, admin, "noret")
    ended = populate(client, admin, "ret", "pid-r1")
    running = populate(client, admin, "ret", "pid-r2")
    elsewhere = populate(client, admin, "noret", "pid-r3")
    finished = datetime(2027, 1, 1, tzinfo=UTC)
    with factory(client).begin() as session:  # two sessions ended on 1 January (completed, as far as it matters)
        for who in (ended, elsewhere):
            row = session.get(Participant, who["id"])
            row.status, row.finished_at = "completed", finished
    before = {r["participant_id"]: r for r in csv_rows(client, admin, "ret", "participants.csv")}
    trials_before = csv_rows(client, admin, "ret", "trials.csv")

    assert sweep_retention(factory(client), now=finished + timedelta(days=29)) == 0  # not due yet
    now = finished + timedelta(days=30, seconds=1)
    assert sweep_retention(factory(client), now=now) == 1
    assert sweep_retention(factory(client), now=now + timedelta(days=1)) == 0  # idempotent
    erased, kept, other = (participant_row(client, w["public_id"]) for w in (ended, running, elsewhere))
    assert (erased.external_id, erased.recruitment, erased.resume_key_hash, erased.survey_draft) == \
        (None, {}, None, None)
    assert erased.personal_data_erased_at == now
    assert kept.external_id == "pid-r2" and kept.personal_data_erased_at is None  # still running
    assert other.external_id == "pid-r3"  # a study without a retention rule

    after = {r["participant_id"]: r for r in csv_rows(client, admin, "ret", "participants.csv")}
    personal = {"external_id", "recruitment", "personal_data_erased_at"}
    for public_id, row in before.items():
        changed = {k for k in row if row[k] != after[public_id][k]}
        assert changed == (personal if public_id == ended["public_id"] else set()), public_id
    assert csv_rows(client, admin, "ret", "trials.csv") == trials_before  # the research data stay
    summary = client.get("/api/admin/studies/ret", headers=auth(admin)).json()["personal_data"]
    assert summary["retention"] == "erased 30 days after each session ends"
    assert summary["erased_sessions"] == 1 and summary["last_erased_at"].startswith("2027-01-31")


def test_a_retention_date_erases_every_ended_session_from_then(world):
    client, admin, _ = world
    open_study(client, admin, "date", erase_personal_on=date(2030, 6, 1))
    who = populate(client, admin, "date", "pid-d1")
    assert client.post(f"/api/p/{who['token']}/withdraw", json={"confirm": True}).status_code == 200
    populate(client, admin, "date", "pid-d2")  # still running
    assert sweep_retention(factory(client), now=datetime(2030, 5, 31, 23, tzinfo=UTC)) == 0
    assert sweep_retention(factory(client), now=datetime(2030, 6, 1, 0, 1, tzinfo=UTC)) == 0  # withdrawal erased it
    declined = populate(client, admin, "date", "pid-d3")
    with factory(client).begin() as session:  # a session that ended without withdrawing
        row = session.get(Participant, declined["id"])
        row.status, row.finished_at = "declined", datetime(2030, 1, 1, tzinfo=UTC)
    assert sweep_retention(factory(client), now=datetime(2030, 6, 1, 0, 2, tzinfo=UTC)) == 1
    summary = client.get("/api/admin/studies/date", headers=auth(admin)).json()["personal_data"]
    assert summary["erase_on"] == "2030-06-01" and summary["erased_sessions"] == 2


def test_pseudonymised_exports_are_stable_per_study_and_differ_across_studies(world, tmp_path: Path):
    client, admin, url = world
    for slug in ("pa", "pb"):
        open_study(client, admin, slug)
        join(client, slug, f"pseudo-key-{slug}-0000000000", PROLIFIC_PID="same-person", SESSION_ID="s-1",
             STUDY_ID="pst")
    first, again = (csv_rows(client, admin, "pa", "participants.csv", pseudonymise="true") for _ in range(2))
    other = csv_rows(client, admin, "pb", "participants.csv", pseudonymise="true")
    plain = csv_rows(client, admin, "pa", "participants.csv")
    assert plain[0]["external_id"] == "same-person"
    hashed = first[0]["external_id"]
    assert len(hashed) == PSEUDONYM_HEX and hashed != "same-person"
    assert again[0]["external_id"] == hashed and other[0]["external_id"] != hashed
    recruitment = json.loads(first[0]["recruitment"])
    assert recruitment["STUDY_ID"] == "pst" and recruitment["PROLIFIC_PID"] == hashed
    assert recruitment["SESSION_ID"] not in ("s-1", hashed)
    assert all("same-person" not in json.dumps(row) for row in first + other)
    archive = client.get("/api/admin/studies/pa/export.zip", params={"pseudonymise": "true"}, headers=auth(admin))
    with zipfile.ZipFile(io.BytesIO(archive.content)) as zipped:
        assert json.loads(zipped.read("manifest.json"))["pseudonymised"] is True
        assert b"same-person" not in zipped.read("participants.csv")
    result = CliRunner().invoke(cli, ["export", "pa", "--out", str(tmp_path / "out"), "--database-url", url,
                                      "--pseudonymise"])
    assert result.exit_code == 0, result.output
    with open(tmp_path / "out" / "participants.csv", encoding="utf-8") as handle:
        assert [r["external_id"] for r in csv.DictReader(handle)] == [hashed]  # the CLI's, the same
    codebook = {r["column"]: r for r in csv_rows(client, admin, "pa", "codebook.csv")
                if r["file"] == "participants.csv"}
    assert "pseudonymised export" in codebook["external_id"]["meaning"]


def test_the_recruitment_id_is_in_no_url_after_the_join(world):
    client, admin, _ = world
    open_study(client, admin, "url")
    page = client.get("/join/url", params={"PROLIFIC_PID": "secret-pid"}, follow_redirects=False)
    assert page.status_code == 200 and "location" not in page.headers  # the page, no redirect echoing it
    joined = join(client, "url", "url-key-00000000000000000", PROLIFIC_PID="secret-pid")  # the id in the body
    assert "secret-pid" not in joined["participant_url"] and "secret-pid" not in json.dumps(joined["state"])
    state = client.get(f"/api/p/{joined['token']}/state")
    assert "secret-pid" not in state.text and "location" not in state.headers
    assert participant_row(client, public_id_of(client, joined["token"])).external_id == "secret-pid"


def test_the_privacy_section_is_left_out_of_dumps_at_its_default():
    """Documents written before it keep their hash; a study that sets it gets it in its document."""
    assert "privacy" not in fast_config().model_dump(mode="json")
    dumped = fast_config().model_copy(update={"privacy": PrivacyConfig(withdrawal="delete")}).model_dump(mode="json")
    assert dumped["privacy"]["withdrawal"] == "delete"


def test_a_withdrawal_text_is_shown_as_the_study_wrote_it(world):
    client, admin, _ = world
    open_study(client, admin, "text", withdrawal_text="Your answers so far are kept, as the consent form said.")
    token = join(client, "text", "text-key-00000000000000000")["token"]
    state = client.get(f"/api/p/{token}/state").json()
    assert state["withdrawal"] == {"data": "keep", "text": "Your answers so far are kept, as the consent form said.",
                                   "by": None}


def test_a_deleted_session_reloads_in_its_language_with_a_title_per_language(world):
    client, admin, _ = world
    config = fast_config()
    texts = config.texts.model_copy(update={"title": {"en": "Robots", "de": "Roboter"}})
    make_study(client, admin, slug="titles", config=config.model_copy(update={
        "languages": ["en", "de"], "texts": texts, "privacy": PrivacyConfig(withdrawal="delete")}))
    who = join(client, "titles", "k-titles-" + "x" * 20, lang="de")
    assert withdraw(client, who["token"])["study_title"] == "Roboter"
    reloaded = client.get(f"/api/p/{who['token']}/state")  # the rows are gone: the state comes from the audit line
    assert reloaded.status_code == 200, reloaded.text
    assert (reloaded.json()["study_title"], reloaded.json()["language"]) == ("Roboter", "de")
