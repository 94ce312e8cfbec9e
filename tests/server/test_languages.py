"""Issue 41: the session's language is chosen once at the join (link parameter, then Accept-Language, then the
study's default), stored on the participant, and kept by every later request (a reload, another browser setting)."""

from __future__ import annotations

import pytest

from tests.server.factories import auth, fast_config, join, make_client, make_study


@pytest.fixture
def api(database_url):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin, config=fast_config(languages=["en", "de", "ar"]))
    return client, admin


def test_the_link_parameter_chooses_and_a_reload_keeps_it(api) -> None:
    client, _ = api
    joined = join(client, lang="de", PROLIFIC_PID="p-de")
    assert joined["state"]["language"] == "de"
    token = joined["token"]
    english = {"Accept-Language": "en"}
    assert client.get(f"/api/p/{token}/state", headers=english).json()["language"] == "de"  # a reload keeps it
    again = join(client, PROLIFIC_PID="p-de")  # the same browser resumes: its language stays
    assert again["token"] == token and again["state"]["language"] == "de"


def test_the_browser_preference_chooses_among_the_studys_languages(api) -> None:
    client, _ = api
    def joined(header: str, **params: str) -> str:
        response = client.post("/api/studies/s1/join", params=params, headers={"Accept-Language": header})
        assert response.status_code == 200, response.text
        return response.json()["state"]["language"]
    assert joined("ar-EG,ar;q=0.9,en;q=0.5") == "ar"
    assert joined("fr-FR,fr;q=0.9,de;q=0.7") == "de"
    assert joined("fr-FR") == "en"  # none offered: the study's default
    assert joined("de", lang="ar") == "ar"  # the link's parameter wins
    assert joined("de", lang="fr") == "de"  # a language the study does not offer is never chosen


def test_a_preview_takes_its_language(api) -> None:
    client, admin = api
    preview = client.post("/api/admin/studies/s1/preview", params={"language": "de"}, headers=auth(admin)).json()
    assert client.get(f"/api/p/{preview['token']}/state").json()["language"] == "de"
    default = client.post("/api/admin/studies/s1/preview", headers=auth(admin)).json()
    assert client.get(f"/api/p/{default['token']}/state").json()["language"] == "en"
