"""Request bodies are standard JSON only (``server.bodies``): refused with 422 and the place, never stored."""

from __future__ import annotations

import pytest

from server import strict_json
from tests.server.factories import join, make_client, make_study

#: The PostgreSQL runs add nothing here (tests/conftest.py): bodies are refused before any handler runs, so nothing
#: reaches the database.
STORAGE_INCIDENTAL = True

DEEP = '{"a":' * 40 + "1" + "}" * 40


@pytest.mark.parametrize(("text", "reason"), [
    ('{"x": NaN}', "NaN is not a JSON number"),
    ('{"x": -Infinity}', "-Infinity is not a JSON number"),
    ('{"x": [1e309]}', "too large"),
    ('{"x": "\\ud800"}', "lone UTF-16 surrogate"),
    ('{"\\udfff": 1}', "lone UTF-16 surrogate"),
    (DEEP, "nested deeper than 32"),
    ("[" * 100_000 + "]" * 100_000, "nested deeper than"),
    ('{"x": 1', "not valid JSON"),
])
def test_strict_loads_refuses_what_exports_cannot_write(text, reason):
    with pytest.raises(strict_json.StrictJsonError, match=reason):
        strict_json.loads(text)


def test_strict_loads_reads_standard_json_and_refuses_other_encodings():
    assert strict_json.loads(b'{"a": [1, 2.5, "\\u00e9\\ud83d\\ude00", null, true]}') == {
        "a": [1, 2.5, "é😀", None, True]}
    with pytest.raises(strict_json.StrictJsonError, match="UTF-8"):
        strict_json.loads('{"a": 1}'.encode("utf-16"))
    with pytest.raises(strict_json.StrictJsonError, match="UTF-8"):
        strict_json.loads(b'{"a": "\xff"}')


def test_check_bounds_keys_strings_and_integers():
    strict_json.check({"a": "x" * 10, "b": 5}, max_keys=2, max_string=10, max_int=5)
    for value, bound in [({"a": 1, "b": 2, "c": 3}, {"max_keys": 2}), ({"a": "x" * 11}, {"max_string": 10}),
                         ({"x" * 11: 1}, {"max_string": 10}), ({"a": [6]}, {"max_int": 5}),
                         ({"a": float("nan")}, {}), ({"a": {1, 2}}, {})]:
        with pytest.raises(strict_json.StrictJsonError):
            strict_json.check(value, **bound)
    with pytest.raises(ValueError):
        strict_json.dumps({"a": float("inf")})


@pytest.mark.parametrize("body", [
    '{"events":[{"kind":"x","payload":{"s":"\\ud800"}}]}',
    '{"events":[{"kind":"x","client_time_ms":1e309}]}',
    '{"events":[{"kind":"x","client_time_ms":NaN}]}',
    '{"events":[{"kind":"x","payload":' + DEEP + '}]}',
    '{"events":[{"kind":"x","payload":' + "[" * 600 + "]" * 600 + '}]}',
])
def test_participant_bodies_that_are_not_standard_json_are_refused_with_the_place(database_url, body):
    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    token = join(client)["token"]
    response = client.post(f"/api/p/{token}/events", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text
    assert response.json()["code"] == "invalid" and response.json()["detail"].startswith("body")


def test_admin_bodies_are_read_strictly_too(database_url):
    client, admin = make_client(database_url=database_url)
    response = client.post("/api/admin/studies", content='{"slug": "s9", "config": {"seed": NaN}}',
                           headers={"content-type": "application/json", "authorization": f"Bearer {admin}"})
    assert response.status_code == 422 and "NaN" in response.json()["detail"]


def test_the_admin_api_refuses_query_parameters_it_does_not_take_and_a_join_link_keeps_its_own(database_url):
    """A mistyped parameter (``include_previews``) is a 422 that names it and what the request takes, not an export
    made without it; a join link carries whatever its recruitment site adds."""
    from tests.server.factories import auth

    client, admin = make_client(database_url=database_url)
    make_study(client, admin)
    refused = client.get("/api/admin/studies/s1/export/trials.csv?include_previews=true", headers=auth(admin))
    assert refused.status_code == 422, refused.text
    assert refused.json() == {"code": "invalid", "detail": "query: unknown parameter(s) 'include_previews'; this "
                                                           "request takes include_preview, pseudonymise"}
    assert client.get("/api/admin/studies/s1/export/trials.csv?include_preview=true",
                      headers=auth(admin)).status_code == 200
    assert client.get("/api/admin/studies?page=2", headers=auth(admin)).status_code == 422
    joined = client.post("/api/studies/s1/join?PROLIFIC_PID=p1&STUDY_ID=x&utm_source=mail", json={})
    assert joined.status_code == 200, joined.text
