"""A participant through a whole study over the HTTP and websocket APIs."""

from contextlib import nullcontext

from experiment.iohmm import paper_params
from server.bots import run_bots
from tests.server.factories import auth, join, make_client, make_study


def test_bots_complete_the_demo(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    summary = run_bots(lambda: nullcontext(client), client.websocket_connect, "s1", paper_params(),
                       participants=2, concurrency=1)
    assert summary.errors == [] and summary.completed == 2
    rows = client.get("/api/admin/studies/s1/participants", headers=auth(admin)).json()
    assert [r["status"] for r in rows] == ["completed", "completed"]


def test_join_twice_with_the_same_external_id_resumes(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    first = join(client, PROLIFIC_PID="abc")
    second = join(client, PROLIFIC_PID="abc")
    assert first["token"] == second["token"] and second["created"] is False
