"""Joining a study. (Bots through a whole study over the HTTP and websocket APIs: test_exports, which checks
every exported row they leave.)"""

from tests.server.factories import join, make_client, make_study


def test_join_twice_with_the_same_external_id_resumes(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    first = join(client, PROLIFIC_PID="abc")
    second = join(client, PROLIFIC_PID="abc")
    assert first["token"] == second["token"] and second["created"] is False
