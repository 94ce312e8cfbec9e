"""Issue 40 in the admin API: a fit request compares numbers of trust states, or fits a model of three or four.

Small data (six simulated participants, two restarts, two folds) keep every fit well under a second.
"""

from __future__ import annotations

import html
import io
import json
import re
import threading
import time
import zipfile

import pytest

from experiment.evaluation import policy_summary
from experiment.iohmm import PARAMETER_NAMES, paper_params
from experiment.model_selection import model_document, select_states
from experiment.records import read_sequences
from experiment.trust_states_document import parameter_names
from experiment.trust_states_em import EMSettings
from server.services import fits
from tests.server.factories import add_simulated_participants, auth, make_study
from tests.server.test_fits import app_client, estimation_config, wait_for_fit  # noqa: F401  (the fixture)

RESTARTS, SEED, FOLDS = 2, 5, 2
STATUSES = {"estimated", "boundary", "unidentified", "not_exercised"}


@pytest.fixture
def study(app_client):  # noqa: F811  (the fixture of the same name)
    client, admin = app_client
    make_study(client, admin, config=estimation_config(), slug="s1")
    add_simulated_participants(client, "s1", n=6, model=paper_params(), seed=1)
    return client, admin


def fit(client, admin, **body):
    return client.post("/api/admin/studies/s1/fits", json={"restarts": RESTARTS, "seed": SEED, **body},
                       headers=auth(admin))


def test_comparing_numbers_of_states_keeps_the_chosen_model_and_the_comparison(study, tmp_path):
    client, admin = study
    started = fit(client, admin, states=[3, 2], folds=FOLDS)
    assert started.status_code == 202, started.text
    model = wait_for_fit(client, admin, started.json()["id"])
    assert model["status"] == "done", model["error"]
    assert model["progress"]["iterations_done"] == model["progress"]["iterations_max"]

    # The same comparison, run directly on the exported trials.csv, gives the same choice and the same model.
    path = tmp_path / "trials.csv"
    path.write_bytes(client.get("/api/admin/studies/s1/export/trials.csv", headers=auth(admin)).content)
    _, sequences = read_sequences(path)
    selection = select_states(sequences, [2, 3], folds=FOLDS, seed=SEED, settings=EMSettings(restarts=RESTARTS))
    document = client.get(f"/api/admin/models/{model['id']}/document", headers=auth(admin)).json()
    assert document == model_document(sequences, selection.chosen, restarts=RESTARTS, seed=SEED,
                                      fitted_on=document["fitted_on"], selection=selection)
    read = model["selection"]
    assert (read["chosen"], read["reason"], read["folds"], read["seed"]) == (
        selection.chosen, selection.reason, FOLDS, SEED)
    assert model["n_states"] == selection.chosen
    for shown, candidate in zip(read["candidates"], selection.candidates, strict=True):
        assert shown == {"n_states": candidate.n_states, "loglik": candidate.loglik, "n_free": candidate.fit.n_free,
                         "bic": candidate.bic, "icl": candidate.icl, "held_out_per_trial": candidate.held_out,
                         "held_out_se": candidate.held_out_se}
    names = PARAMETER_NAMES if selection.chosen == 2 else parameter_names(selection.chosen)
    assert [p["name"] for p in model["parameters"]] == names

    # The states and the folds are part of the request's identity: a retry finds it, other folds fit again.
    assert fit(client, admin, states=[2, 3], folds=FOLDS).json()["id"] == model["id"]
    assert fit(client, admin, states=[2, 3], folds=FOLDS).status_code == 200
    other = fit(client, admin, states=[2, 3], folds=3)
    assert other.status_code == 202 and other.json()["id"] != model["id"]
    wait_for_fit(client, admin, other.json()["id"])
    assert fit(client, admin).json()["id"] not in (model["id"], other.json()["id"])  # no states: today's fit


def test_a_three_state_model_reads_and_deploys(study):
    client, admin = study
    model = wait_for_fit(client, admin, fit(client, admin, states=[3]).json()["id"])
    assert model["status"] == "done", model["error"]
    assert model["n_states"] == 3 and model["selection"] is None
    assert [p["name"] for p in model["parameters"]] == parameter_names(3)
    assert {p["status"] for p in model["parameters"]} <= STATUSES
    for p in model["parameters"]:
        assert p["stderr"] is None or p["status"] == "estimated"
    assert model["loglik"] < 0 and model["converged"] is not None
    policy = model["policy"]
    assert policy["error"] is None and policy["n_states"] == 3 and policy["threshold"] is None
    assert set(policy["ask_share"]) == {"low", "high"} and all(0 <= v <= 1 for v in policy["ask_share"].values())
    assert model["evaluation_blocked"] is None
    created = client.post(f"/api/admin/models/{model['id']}/evaluation-study",
                          json={"slug": "eval3", "template": "demo-fast"}, headers=auth(admin))
    assert created.status_code == 201, created.text
    assert created.json()["config"]["model"]["n_states"] == 3


def test_bad_numbers_of_states_or_folds_are_refused_with_the_reason(study):
    client, admin = study
    for bad, words in (({"states": [1, 2]}, "greater than or equal to 2"),
                       ({"states": [2, 5]}, "less than or equal to 4"), ({"states": [2, 2]}, "distinct"),
                       ({"states": []}, "at least 1"), ({"states": "2,3"}, "list"), ({"folds": 1}, "2"),
                       ({"folds": 21}, "20"), ({"states": [2, 3], "folds": 2.5}, "integer")):
        response = fit(client, admin, **bad)
        assert response.status_code == 422, (bad, response.text)
        assert words in response.text, (bad, response.text)
    too_many = fit(client, admin, states=[2, 3], folds=7)
    assert too_many.status_code == 409
    assert "needs at least 7 participants, the data have 6" in too_many.json()["detail"]


def test_stopping_the_server_interrupts_a_comparison_within_a_fit(study, monkeypatch):
    client, admin = study
    started = threading.Event()

    def endless(*args, progress, **kwargs):  # one fit of the comparison that never ends
        started.set()
        while True:
            progress(1, 10)
            time.sleep(0.01)

    monkeypatch.setattr("experiment.model_selection.fit_k_states", endless)
    model = fit(client, admin, states=[2, 3], folds=FOLDS).json()
    assert started.wait(60)
    client.app.state.services.fits.stop()  # what the server's shutdown does
    stopped = client.get(f"/api/admin/models/{model['id']}", headers=auth(admin)).json()
    assert stopped["status"] == "failed" and stopped["error"] == fits.INTERRUPTED


def test_the_report_of_a_model_chosen_by_comparison_shows_the_comparison(study):
    client, admin = study
    model = wait_for_fit(client, admin, fit(client, admin, states=[2, 3], folds=FOLDS).json()["id"])
    selection = model["selection"]
    assert selection["chosen"] == 2  # six participants of the paper's two-state model

    page = client.get(f"/api/admin/studies/s1/report.html?model={model['id']}", headers=auth(admin))
    assert page.status_code == 200, page.text
    section = page.text.split("<section id='selection'>", 1)[1].split("</section>", 1)[0]
    assert "<h2>Which model the data support</h2>" in section
    assert f"Chosen: {html.escape(selection['reason'])}." in section
    rows = re.findall(r"<tr>(.*?)</tr>", section.split("<tbody>", 1)[1].split("</tbody>", 1)[0],
                      flags=re.S)
    assert len(rows) == 2 and sum("chosen" in r for r in rows) == 1
    assert "data:image/png;base64," in section  # the figure, inlined
    assert "Held-out log-likelihood per trial by number of trust states" in section

    archive = client.get(f"/api/admin/studies/s1/report?model={model['id']}", headers=auth(admin))
    assert archive.status_code == 200
    with zipfile.ZipFile(io.BytesIO(archive.content)) as zf:
        key = json.loads(zf.read("report.json"))
        assert "figures/selection_held_out.png" in zf.namelist()
        assert json.loads(zf.read("model.json"))["selection"]["reason"] == selection["reason"]
    assert key["selection"]["chosen"] == 2 and key["selection"]["reason"] == selection["reason"]
    assert [c["n_states"] for c in key["selection"]["candidates"]] == [2, 3]

    plain = client.get("/api/admin/studies/s1/report.html", headers=auth(admin))  # fitted here: no comparison
    assert plain.status_code == 200 and "<section id='selection'>" not in plain.text


def test_the_report_of_a_three_state_model_shows_its_parameters_and_policy(study):
    client, admin = study
    k3 = wait_for_fit(client, admin, fit(client, admin, states=[3]).json()["id"])
    page = client.get(f"/api/admin/studies/s1/report.html?model={k3['id']}", headers=auth(admin))
    assert page.status_code == 200, page.text
    model = page.text.split("<section id='model'>", 1)[1].split("</section>", 1)[0]
    assert "<h2>The trust model: 3 trust states</h2>" in model
    assert re.findall(r"<tr><td>([a-z_0-9.]+)</td><td>P\(", model) == parameter_names(3)
    for p in k3["parameters"]:  # the document's estimates and standard errors, as the API reads them
        row = re.search(rf"<tr><td>{re.escape(p['name'])}</td><td>.*?</td><td[^>]*>(.*?)</td><td[^>]*>(.*?)</td>",
                        model)
        assert row is not None and row.group(2) == ("—" if p["stderr"] is None else f"{p['stderr']:.3f}"), p
    policy = page.text.split("<section id='policy'>", 1)[1].split("</section>", 1)[0]
    assert "Where the robot asks: in low complexity it " in html.unescape(policy)
    assert "Trust-aware policy on the belief simplex (3 states)" in policy and "data:image/png;base64," in policy
    shown = json.loads(re.search(r"id='key-figures'>(.*?)</script>", page.text).group(1))["policy"]
    document = client.get(f"/api/admin/models/{k3['id']}/document", headers=auth(admin)).json()
    # The policy the dashboard shows for the model (evaluation.policy_summary), at the report's p_high.
    assert shown["ask_share"] == pytest.approx(policy_summary(document, shown["p_high"])["ask_share"])
    missing = client.get("/api/admin/studies/s1/report.html?model=999", headers=auth(admin))
    assert missing.status_code == 404


def test_a_fit_with_the_trust_ratings_keeps_their_emission_and_what_they_add(app_client, tmp_path):  # noqa: F811
    import numpy as np

    from experiment.model_selection import fit_with_ratings
    from experiment.trust_ratings import RatingEmission, read_rated_sequences

    client, admin = app_client
    make_study(client, admin, config=estimation_config(), slug="s1")
    emission = RatingEmission(np.array([3.0, 12.0]), np.array([12.0, 3.0]))
    add_simulated_participants(client, "s1", n=6, model=paper_params(), seed=1, ratings=emission)
    started = fit(client, admin, with_ratings=True, folds=FOLDS)
    assert started.status_code == 202, started.text
    assert fit(client, admin, with_ratings=True, folds=FOLDS).json()["id"] == started.json()["id"]  # the same request
    model = wait_for_fit(client, admin, started.json()["id"])
    assert model["status"] == "done", model["error"]
    ratings = model["ratings"]
    assert ratings["n_ratings"] == 6 * 9 and ratings["scale"] == [0, 10] and len(ratings["mean_rating"]) == 2
    assert ratings["comparison"]["verdict"].startswith("the ratings ")

    # The same fit, run on the export's trials.csv and surveys.csv, gives the same model.
    for name in ("trials.csv", "surveys.csv"):
        (tmp_path / name).write_bytes(client.get(f"/api/admin/studies/s1/export/{name}", headers=auth(admin)).content)
    participants, sequences, read = read_rated_sequences(tmp_path / "trials.csv", tmp_path / "surveys.csv")
    document = client.get(f"/api/admin/models/{model['id']}/document", headers=auth(admin)).json()
    direct = fit_with_ratings(sequences, read, [2], restarts=RESTARTS, seed=SEED, folds=FOLDS,
                              fitted_on=document["fitted_on"]).document
    assert json.loads(json.dumps(direct)) == document

    page = client.get(f"/api/admin/studies/s1/report.html?model={model['id']}", headers=auth(admin))
    assert page.status_code == 200, page.text
    added = html.unescape(page.text.split("<section id='ratings'>", 1)[1].split("</section>", 1)[0])
    verdict = ratings["comparison"]["verdict"]
    assert "<h2>What the trust ratings add</h2>" in added and f"{verdict[0].upper()}{verdict[1:]}." in added
    assert f"<td>state 1</td><td class=num>{ratings['mean_rating'][1]:.1f}</td>" in added


def test_a_fit_with_ratings_of_a_study_without_them_is_refused(study):
    client, admin = study
    refused = fit(client, admin, with_ratings=True, folds=FOLDS)
    assert refused.status_code == 409 and "no trust rating" in refused.json()["detail"]


def test_a_fit_with_ratings_of_a_study_that_asks_no_trust_rating_says_so(app_client):  # noqa: F811
    client, admin = app_client
    make_study(client, admin, config=estimation_config(shelf_questionnaire=None), slug="s1")
    add_simulated_participants(client, "s1", n=3, model=paper_params(), seed=1)
    refused = fit(client, admin, with_ratings=True, folds=FOLDS)
    assert refused.status_code == 409 and "asks no trust rating" in refused.json()["detail"]
