"""Issue 36: an external id identifies a participant but claims no session, and bare joins cannot fill a study.

Each TestClient here is one browser (its own resume key, as the join page keeps one in localStorage) at its own
address; the attacker knows the owner's id (a lab's pid=1, a PROLIFIC_PID from a shared participants.csv).
"""

from __future__ import annotations

import csv
import io
import threading
from datetime import timedelta

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from experiment.config import RecruitmentConfig
from server.models import Participant, Study, utcnow
from server.services import joining, sessions
from tests.server.factories import auth, browser_key, fast_config, join, make_client, make_study


def browser(client: TestClient, address: str) -> TestClient:
    """Another browser on the same server, at ``address``."""
    return TestClient(client.app, client=(address, 40000))


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    return client, admin


def participants(client: TestClient, admin: str) -> dict[str, dict]:
    listed = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()
    return {p["public_id"]: p for p in listed}


def exported(client: TestClient, admin: str) -> dict[str, dict]:
    text = client.get("/api/admin/studies/s1/export/participants.csv", headers=auth(admin)).text
    return {row["participant_id"]: row for row in csv.DictReader(io.StringIO(text))}


def public_id(client: TestClient, token: str) -> str:
    with client.app.state.services.sessionmaker() as session:
        return session.scalar(select(Participant.public_id).where(Participant.token_hash == sessions.hash_token(token)))


def flags(row: dict) -> list[str]:
    return [flag["code"] for flag in row["flags"]]


def test_an_id_alone_gets_a_flagged_duplicate_never_the_owners_token(api):
    owner, admin = api
    mine = join(owner, PROLIFIC_PID="5f3a-owner")
    owner.post(f"/api/p/{mine['token']}/consent", json={"agree": True})

    for param in ("PROLIFIC_PID", "pid", "participant", "workerId"):  # one namespace: any parameter with the value
        theirs = join(browser(owner, "198.51.100.9"), **{param: "5f3a-owner"})
        assert theirs["token"] != mine["token"] and theirs["created"] is True
        assert theirs["state"]["phase"] == "consent"  # a session of their own, from the start
    bare = owner.post("/api/studies/s1/join", params={"PROLIFIC_PID": "5f3a-owner"})  # no key at all (curl)
    assert bare.json()["token"] != mine["token"] and bare.json()["created"] is True

    again = join(owner, PROLIFIC_PID="5f3a-owner")  # the owner's browser (its resume key) resumes
    assert again["token"] == mine["token"] and again["created"] is False and again["state"]["phase"] == "instructions"

    first = public_id(owner, mine["token"])
    rows = participants(owner, admin)
    assert len(rows) == 6 and all(flags(row) == ["duplicate_id"] for row in rows.values())
    assert "also joined as" in rows[first]["flags"][0]["detail"]
    csv_rows = exported(owner, admin)
    assert csv_rows[first]["duplicate_of"] == ""
    assert {row["duplicate_of"] for pid, row in csv_rows.items() if pid != first} == {first}
    codebook = owner.get("/api/admin/studies/s1/export/codebook.csv", headers=auth(admin)).text
    assert "duplicate_of" in codebook


def test_a_pre_claimed_id_does_not_capture_the_owners_later_data(api):
    owner, admin = api
    squatter = browser(owner, "198.51.100.9")
    claimed = join(squatter, pid="7")  # a guessable lab id, claimed before its owner arrives
    arrived = join(owner, pid="7")
    assert arrived["created"] is True and arrived["token"] != claimed["token"]

    assert owner.post(f"/api/p/{arrived['token']}/consent", json={"agree": True}).status_code == 200
    assert squatter.get(f"/api/p/{claimed['token']}/state").json()["phase"] == "consent"  # sees none of it
    assert join(squatter, pid="7")["token"] == claimed["token"]  # and rejoining gives back only its own
    assert join(owner, pid="7")["token"] == arrived["token"]
    squatter_id = public_id(owner, claimed["token"])
    assert exported(owner, admin)[public_id(owner, arrived["token"])]["duplicate_of"] == squatter_id
    assert flags(participants(owner, admin)[squatter_id]) == ["duplicate_id"]  # both are flagged: who is whom is open


def test_an_ended_sessions_id_resumes_its_end_for_its_browser_and_is_a_new_session_for_anyone_else(api):
    owner, _ = api
    other = browser(owner, "198.51.100.9")
    declined = join(owner, PROLIFIC_PID="done")
    owner.post(f"/api/p/{declined['token']}/consent", json={"agree": False})

    back = join(owner, PROLIFIC_PID="done")
    assert back["token"] == declined["token"] and back["state"]["phase"] == "declined"  # shows its end again
    fresh = join(other, PROLIFIC_PID="done")  # someone else: never locked out, never the ended session
    assert fresh["created"] is True and fresh["token"] != declined["token"] and fresh["state"]["phase"] == "consent"


def test_the_same_prolific_session_resumes_from_another_browser(api):
    laptop, admin = api
    phone, stranger = browser(laptop, "203.0.113.5"), browser(laptop, "198.51.100.9")
    link = {"PROLIFIC_PID": "60aa", "STUDY_ID": "st", "SESSION_ID": "s-9f2c"}
    mine = join(laptop, **link)

    assert join(phone, **link)["token"] == mine["token"]  # the participant reopened the study from Prolific
    assert join(phone, resume_key=None, **link)["token"] == mine["token"]
    assert join(stranger, **(link | {"SESSION_ID": "s-other"}))["token"] != mine["token"]
    # SESSION_ID pairs with PROLIFIC_PID
    assert join(stranger, pid="60aa", SESSION_ID="s-9f2c")["token"] != mine["token"]
    # MTurk: the assignment is the sitting; the preview's placeholder names nobody
    worker = join(laptop, workerId="A1", assignmentId="3X")
    assert join(stranger, workerId="A1", assignmentId="3X")["token"] == worker["token"]
    previewed = join(laptop, workerId="A2", assignmentId="ASSIGNMENT_ID_NOT_AVAILABLE")
    assert join(stranger, workerId="A2", assignmentId="ASSIGNMENT_ID_NOT_AVAILABLE")["token"] != previewed["token"]


def test_a_retried_or_doubled_first_join_of_one_browser_resumes(api):
    client, _ = api
    key = browser_key(client)
    first = client.post("/api/studies/s1/join", params={"pid": "12"}, json={"resume_key": key}).json()
    assert first["resume_key"] == key  # the key in effect comes back
    again = client.post("/api/studies/s1/join", params={"pid": "12"}, json={"resume_key": key}).json()
    assert again["token"] == first["token"]
    bare = client.post("/api/studies/s1/join", params={"pid": "13"}).json()  # no key sent: the server makes one
    assert len(bare["resume_key"]) >= 22
    resumed = client.post("/api/studies/s1/join", params={"pid": "13"}, json={"resume_key": bare["resume_key"]})
    assert resumed.json()["token"] == bare["token"]
    weak = client.post("/api/studies/s1/join", params={"pid": "14"}, json={"resume_key": "short"})
    assert weak.status_code == 422 and "resume_key" in weak.text


def capped(database_url, cap: int, **settings):
    client, admin = make_client(database_url=database_url, **settings)
    make_study(client, admin, config=fast_config(recruitment=RecruitmentConfig(max_active_participants=cap)))
    return client, admin


def quiet_for(client: TestClient, seconds: float) -> None:
    """Every session was last seen ``seconds`` ago."""
    with client.app.state.services.sessionmaker.begin() as session:
        session.execute(update(Participant).values(last_seen_at=utcnow() - timedelta(seconds=seconds)))


def test_bare_joins_do_not_fill_the_cap(database_url):
    client, _ = capped(database_url, 3)
    addresses = [browser(client, f"192.0.2.{i}") for i in range(3)]
    consented = join(addresses[0])
    assert addresses[0].post(f"/api/p/{consented['token']}/consent", json={"agree": True}).status_code == 200
    join(addresses[1]), join(addresses[2])  # two bare joins: never a consent, never another request
    assert browser(client, "192.0.2.50").post("/api/studies/s1/join").status_code == 503  # for now, they hold places

    quiet_for(client, 121)  # past the unconsented hold (120 s by default), far below the 15 min idle timeout
    assert join(browser(client, "192.0.2.51"))["created"] is True
    assert join(browser(client, "192.0.2.52"))["created"] is True
    refused = browser(client, "192.0.2.53").post("/api/studies/s1/join")  # the consented one kept its place
    assert refused.status_code == 503 and refused.json()["code"] == "study_full"


def test_one_address_holds_few_unconsented_places_and_a_lab_behind_one_nat_runs_many(database_url):
    client, _ = capped(database_url, 50, max_unconsented_per_address=2)
    lab = browser(client, "192.0.2.1")
    tokens = [join(lab)["token"] for _ in range(2)]
    refused = lab.post("/api/studies/s1/join")
    assert refused.status_code == 429 and refused.json()["code"] == "address_busy"
    retry_after = int(refused.headers["Retry-After"])
    assert 1 <= retry_after <= 120 and refused.json()["retry_after_s"] == retry_after
    assert "consent" in refused.json()["detail"]
    assert join(browser(client, "192.0.2.2"))["created"] is True  # another address is not held back

    for _ in range(10):  # as each participant consents, the next at the same address joins: no cap on the lab
        assert lab.post(f"/api/p/{tokens.pop(0)}/consent", json={"agree": True}).status_code == 200
        tokens.append(join(lab)["token"])
    with client.app.state.services.sessionmaker() as session:
        assert session.scalar(select(Participant.join_address_hash).where(Participant.consented_at.is_not(None))
                              .limit(1)) is None  # the address is kept until consent only


def test_two_browsers_joining_with_one_new_id_at_once_get_one_session_each(api):
    client, admin = api
    browsers = [browser(client, f"192.0.2.{i}") for i in range(4)]
    keys, ready, answers = [browser_key(b) for b in browsers], threading.Barrier(4), []

    def one(index: int) -> None:
        ready.wait()
        answers.append(client.post("/api/studies/s1/join", params={"pid": "race"}, json={"resume_key": keys[index]}))

    with client:  # one event loop for every thread (PostgreSQL units run concurrently in worker threads)
        threads = [threading.Thread(target=one, args=(i,)) for i in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert [a.status_code for a in answers] == [200] * 4 and len({a.json()["token"] for a in answers}) == 4
    duplicates = sorted(row["duplicate_of"] for row in exported(client, admin).values())
    assert duplicates[0] == "" and len(set(duplicates[1:])) == 1 and duplicates[1] != ""  # one first, three of it


def test_a_session_from_before_resume_keys_resumes_by_its_prolific_session(api):
    client, _ = api
    link = {"PROLIFIC_PID": "old-timer", "SESSION_ID": "s-old"}
    joined = join(client, **link)
    # as revision 0007 left it: token from the id, no key
    with client.app.state.services.sessionmaker.begin() as session:
        participant = session.scalar(select(Participant).where(Participant.external_id == "old-timer"))
        legacy = joining._session_token(session, session.get(Study, participant.study_id), "old-timer")
        participant.token_hash, participant.resume_key_hash = sessions.hash_token(legacy), None
    assert join(browser(client, "192.0.2.9"), **link)["token"] == legacy != joined["token"]
    assert join(client, PROLIFIC_PID="old-timer")["token"] != legacy  # the id alone: someone new
