"""The report of a model of three trust states (issue 40), and of a model fitted with trust ratings.

A simulated export of the illustrative three-state model, a three-state model fitted to it (two restarts: the fit
itself is tested in test_model_selection.py), and ``trustlab report --model m3.json`` on it.
"""

from __future__ import annotations

import json
import math
import re
from html import unescape
from pathlib import Path

import pytest
from typer.testing import CliRunner

from experiment.config import TrustAwareSpec
from experiment.engine import simplex_resolution
from experiment.model_selection import model_document
from experiment.records import read_sequences
from experiment.report import build_report
from experiment.report.content import Paragraph, TableBlock, fmt
from experiment.report.model import _dotted
from experiment.report.selection import selection_section
from experiment.task import TaskParams
from experiment.trust_states import illustrative_three_state_model, log_likelihood_k
from experiment.trust_states_document import k_state_document, k_state_params_from_document, parameter_names
from experiment.trust_states_policy import ask_share, describe, solve_k_state_policy
from server.cli import app
from tests.experiment.report_data import write_simulated_export
from tests.experiment.test_report import assert_not_blank, key_figures, text

K_FIGURES = {"fig_states_reliance", "fig_states_transitions", "fig_policy_simplex"}
runner = CliRunner()


@pytest.fixture(scope="module")
def three_states(tmp_path_factory):
    root = tmp_path_factory.mktemp("states")
    data = root / "data"
    write_simulated_export(data, "model-estimation", 8, seed=2, model=illustrative_three_state_model())
    _, sequences = read_sequences(data / "trials.csv")
    document = model_document(sequences, 3, restarts=2, seed=0, fitted_on={"source": "data/trials.csv"})
    model = root / "m3.json"
    model.write_text(json.dumps(document), encoding="utf-8")
    result = runner.invoke(app, ["report", str(data), "--out", str(root / "report"), "--model", str(model), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    page = (root / "report" / "report.html").read_text(encoding="utf-8")
    return data, sequences, document, summary, page


def section(page: str, key: str) -> str:
    return page.split(f"<section id='{key}'>", 1)[1].split("</section>", 1)[0]


def test_the_model_section_tables_every_parameter_as_the_document_holds_it(three_states):
    _, sequences, document, _, page = three_states
    model = section(page, "model")
    assert "<h2>The trust model: 3 trust states</h2>" in model
    rows = re.findall(r"<tr><td>([a-z_0-9.]+)</td><td>(P\(.*?)</td><td(?: class=num)?>(.*?)</td>"
                      r"<td(?: class=num)?>(.*?)</td><td>(.*?)</td></tr>", model)
    names = parameter_names(3)
    assert [r[0] for r in rows] == names
    values = _dotted(document["params"], names)
    stderr, status = _dotted(document["stderr"], names), _dotted(document["status"], names)
    for name, _label, value, se, shown_status in rows:
        assert value == fmt(math.nan if values[name] is None else values[name])
        assert se == (fmt(stderr[name]) if status[name] == "estimated" else "—")
        assert {"estimated": "estimated", "boundary": "on the boundary (0 or 1)",
                "unidentified": "not identified by the data",
                "not_exercised": "not exercised by the data"}[status[name]] == unescape(shown_status)
    assert unescape(rows[names.index("transitions.low.auto.positive.from_state_1.to_state_2")][1]) == (
        "P(T′ = state 2 | T = state 1, E′ = E+, C = low, a = auto)")
    assert any(s == "estimated" for s in status.values()) and any(se != "—" for *_, se, _ in rows)
    figures = key_figures(page)["model"]
    params = k_state_params_from_document(document)
    assert figures["n_states"] == 3 and figures["loglik"] == pytest.approx(log_likelihood_k(params, sequences))
    assert "Figure 1. Reliance by trust state (3 states)" in text(model)
    assert "Figure 2. Trust transitions (3 states)" in text(model)


def test_the_report_draws_reliance_transitions_and_the_policy_simplex(three_states):
    *_, summary, _ = three_states
    figures = {p.rsplit("/", 1)[1].removesuffix(".png"): p for p in summary["figures"]}
    assert K_FIGURES <= set(figures)
    assert not {"fig4_emissions", "fig_policy"} & set(figures)  # the two-state figures have no meaning here
    for name in K_FIGURES:
        assert_not_blank(Path(figures[name]))


def test_the_policy_section_says_where_the_robot_asks(three_states):
    _, sequences, document, summary, page = three_states
    policy = section(page, "policy")
    words = text(policy)
    p_high = sum(int(s.complexity.sum()) for s in sequences) / sum(len(s) for s in sequences)
    resolution = simplex_resolution(3, TrustAwareSpec.model_fields["grid"].default)
    solution = solve_k_state_policy(k_state_params_from_document(document), TaskParams(), p_high=p_high,
                                    resolution=resolution)
    figures = summary["key_figures"]["policy"]
    assert figures["resolution"] == resolution and figures["grid_points"] == len(solution.beliefs)
    assert figures["description"] == describe(solution)
    assert figures["ask_share"] == pytest.approx({c.value: v for c, v in ask_share(solution).items()})
    assert "Where the robot asks: in low complexity it " in words and "; in high complexity it " in words
    for c, share in ask_share(solution).items():
        if share == 1.0:
            assert f"in {c.value} complexity it always asks" in words
        elif share == 0.0:
            assert f"in {c.value} complexity it always acts alone" in words
        else:
            shown = re.search(rf"in {c.value} complexity it asks on ([\d.]+)% of the belief simplex", words)
            assert shown is not None and 0 < float(shown.group(1)) < 100
            assert float(shown.group(1)) == pytest.approx(100 * share, abs=0.5)
    assert "Figure 3. Trust-aware policy on the belief simplex (3 states)" in words
    assert "threshold" not in figures and "Trust-agnostic baseline" in words


def test_a_policy_between_asking_and_acting_alone_is_said_with_its_beliefs(tmp_path):
    write_simulated_export(tmp_path / "data", "model-estimation", 3, seed=1, model=illustrative_three_state_model())
    model = tmp_path / "m3.json"
    model.write_text(json.dumps(k_state_document(illustrative_three_state_model())), encoding="utf-8")
    report = build_report(tmp_path / "data", model=model, p_high=0.5)
    words = text(report.inline_html())
    share = key_figures(report.inline_html())["policy"]["ask_share"]["high"]
    assert 0.0 < share < 1.0  # the illustrative model asks in high complexity unless trust is surely high
    assert re.search(r"in high complexity it asks on [\d.]+% of the belief simplex: on average where it asks the "
                     r"belief puts [\d.]+ on the lowest trust state and [\d.]+ on the highest, where it acts alone",
                     words)
    assert "as given (no status in the model file)" in words  # a hand-written document has no standard errors


RATINGS = {"emission": "beta-binomial", "item": "trust", "scale": [0, 10], "alpha": [3.0, 6.0, 12.0],
           "beta": [12.0, 6.0, 3.0], "mean_rating": [2.0, 5.0, 8.0], "sd_rating": [1.8, 2.3, 1.7], "n_ratings": 72}
COMPARISON = {"n_states": 3, "n_ratings": 72, "scored": "held-out reliance only", "held_out_with_ratings": -0.3012,
              "held_out_without_ratings": -0.3123, "difference_per_trial": 0.0111, "difference_se": 0.0031,
              "verdict": "the ratings improve the model of reliance (+0.0111 ± 0.0031 per held-out trial, beyond 2 "
                         "standard errors)", "participant_scores_with": [], "participant_scores_without": []}


def test_a_model_fitted_with_ratings_says_what_they_add(three_states, tmp_path):
    data, _, document, _, _ = three_states
    model = tmp_path / "rated.json"
    model.write_text(json.dumps({**document, "ratings": RATINGS, "ratings_comparison": COMPARISON}), encoding="utf-8")
    page = build_report(data, model=model).inline_html()
    assert "<section id='selection'>" not in page  # one number of states: nothing was chosen
    words = text(section(page, "ratings"))
    assert words.startswith(" What the trust ratings add ")
    assert ("The ratings improve the model of reliance (+0.0111 ± 0.0031 per held-out trial, beyond 2 standard "
            "errors).") in words
    assert "with the ratings -0.3012 without the ratings -0.3123" in words
    assert "state 0 2.0 1.8 state 1 5.0 2.3 state 2 8.0 1.7" in words and "Mean rating (0–10)" in words
    assert key_figures(page)["ratings"]["mean_rating"] == RATINGS["mean_rating"]

    selection = {"chosen": 3, "reason": "3 states: the smallest number within one SE of the best", "folds": 2,
                 "seed": 0, "candidates": [
                     {"n_states": k, "loglik": -150.0 - k, "n_free": 10 * k, "bic": 400.0, "icl": 410.0,
                      "held_out_per_trial": -0.31 + k / 1000, "held_out_se": 0.01} for k in (2, 3)]}
    chosen = selection_section({**document, "selection": selection, "ratings": RATINGS,
                                "ratings_comparison": COMPARISON})
    assert chosen is not None and chosen.key == "selection"  # with a comparison of numbers of states: inside it
    words = " ".join(b.text for b in chosen.blocks if isinstance(b, Paragraph))
    assert "Chosen: 3 states" in words and "What the trust ratings add: this model was fitted" in words
    assert "The ratings improve the model of reliance" in words
    [by_state] = [b for b in chosen.blocks if isinstance(b, TableBlock) and b.caption == "Trust rating by trust state"]
    assert by_state.rows[2] == ["state 2", "8.0", "1.7"]
    assert chosen.figures["ratings"]["verdict"] == COMPARISON["verdict"]

    plain = three_states[-1]  # the same model without ratings
    assert "trust ratings add" not in plain and "<section id='ratings'>" not in plain
