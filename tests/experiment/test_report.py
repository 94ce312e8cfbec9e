"""The analysis report on simulated studies: figures exist and show something, numbers match the analysis."""

from __future__ import annotations

import base64
import csv
import hashlib
import json
import re
from collections import defaultdict
from html import unescape
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from experiment.analysis import fit_linear, fit_logistic, median_by_answer, ttest2
from experiment.belief_mdp import solve_belief_mdp
from experiment.fit import fit_iohmm
from experiment.instruments import SCHAEFER_14
from experiment.iohmm import paper_params
from experiment.questionnaires import score
from experiment.records import DataError, read_sequences
from experiment.report import build_report
from experiment.report.html import STYLE, content_security_policy
from experiment.report.plots import new_figure, to_png
from experiment.task import Complexity
from tests.experiment.report_data import write_simulated_export

RESTARTS = 3  # small: the fit itself is tested in test_fit.py
MODEL_FIGURES = {"fig4_emissions", "fig5_transitions_low", "fig6_transitions_high"}


def key_figures(page: str) -> dict:
    return json.loads(re.search(r"<script type='application/json' id='key-figures'>(.*?)</script>", page).group(1))


def text(page: str) -> str:
    return unescape(re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", page)))


def assert_not_blank(png: Path) -> None:
    pixels = (imread(png)[..., :3] * 255).astype(np.uint32)
    assert pixels.shape[0] > 200 and pixels.shape[1] > 300
    assert pixels.std() > 12, f"{png.name} is (nearly) blank"
    coloured = (pixels.max(axis=2) - pixels.min(axis=2)) > 15  # data are drawn in colour, frames and text in grey
    assert coloured.mean() > 0.005, f"{png.name} shows no data (only {coloured.mean():.2%} coloured pixels)"


def surveys(directory: Path) -> list[dict[str, str]]:
    with (directory / "surveys.csv").open(encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture(scope="module")
def estimation(tmp_path_factory):
    data = tmp_path_factory.mktemp("estimation") / "data"
    sim = write_simulated_export(data, "model-estimation", 8, seed=2, declined=1, excluded=("sim-0008",))
    report = build_report(data, restarts=RESTARTS, seed=0)
    files = report.write(data.parent / "report")
    return data, sim, report, files


@pytest.fixture(scope="module")
def evaluation(tmp_path_factory):
    data = tmp_path_factory.mktemp("evaluation") / "data"
    sim = write_simulated_export(data, "policy-evaluation", 6, seed=5)
    report = build_report(data, restarts=RESTARTS, seed=0)
    files = report.write(data.parent / "report")
    return data, sim, report, files


def test_model_estimation_report_has_every_figure_and_says_what_does_not_apply(estimation):
    _, _, report, files = estimation
    names = {p.stem for p in files.figures}
    assert names == MODEL_FIGURES | {"fig_policy", "fig_belief_vs_trust", "fig_reliance_vs_trust"}
    for png in files.figures:
        assert_not_blank(png)
    page = files.html.read_text(encoding="utf-8")
    for png in files.figures:
        assert f"src='figures/{png.name}'" in page
    words = text(page)
    assert "Policy comparison not applicable for this design: it has one block" in words
    assert "Schaefer trust scores not applicable for this design" in words
    assert "Traceback" not in words
    assert json.loads(files.key_figures.read_text()) == key_figures(page)
    assert json.loads(files.model.read_text())["format"] == "trustlab-iohmm"


def test_model_numbers_are_those_of_the_fit_and_no_se_without_one(estimation):
    data, _, report, files = estimation
    _, sequences = read_sequences(data / "trials.csv")
    fit = fit_iohmm(sequences, restarts=RESTARTS, seed=0)
    page = files.html.read_text(encoding="utf-8")
    figures = key_figures(page)["model"]
    assert figures["loglik"] == pytest.approx(fit.loglik, abs=1e-9)
    assert figures["n_participants"] == 7  # the excluded participant is left out
    assert f"{fit.loglik:.3f}" in text(page)
    rows = re.findall(r"<tr><td>(P\(.*?)</td><td class=num>(.*?)</td><td(?: class=num)?>(.*?)</td><td>(.*?)</td>", page)
    assert len(rows) >= 15
    for label, _estimate, se, status in rows:
        assert (se == "—") == (status != "estimated"), (label, se, status)
    assert fit.status.count("boundary") == sum(1 for *_, status in rows if "boundary" in status)


def test_policy_threshold_is_the_belief_mdp_solution(estimation):
    data, _, report, files = estimation
    _, sequences = read_sequences(data / "trials.csv")
    fit = fit_iohmm(sequences, restarts=RESTARTS, seed=0)
    figures = key_figures(files.html.read_text(encoding="utf-8"))["policy"]
    assert figures["p_high"] == pytest.approx(30 / 71)  # the design's 41 low + 30 high trials
    solution = solve_belief_mdp(fit.params, p_high=30 / 71)
    for c in Complexity:
        expected = solution.thresholds[c]
        assert figures["threshold"][c.value] == (pytest.approx(expected) if expected is not None else None)


def test_belief_and_reliance_fits_equal_the_analysis_functions(estimation):
    data, _, _, files = estimation
    page = files.html.read_text(encoding="utf-8")
    shelf = defaultdict(dict)
    for row in surveys(data):
        if row["context"].startswith("shelf:") and row["excluded"] == "0":
            shelf[(row["participant_id"], row["context"])][row["item"]] = (float(row["value"]), float(row["belief"]))
    trust = np.array([s["trust"][0] for s in shelf.values()])
    belief = np.array([s["trust"][1] for s in shelf.values()])
    reliance = np.array([s["reliance"][0] for s in shelf.values()])
    logistic = fit_logistic(*median_by_answer(trust, belief))
    shown = key_figures(page)["trust"]
    for name in ("L", "k", "r0", "sse", "rmse"):
        assert shown["logistic"][name] == pytest.approx(getattr(logistic, name), rel=1e-12)
    words = text(page)
    for value in (logistic.L, logistic.k, logistic.r0, logistic.sse, logistic.rmse):
        assert f"{value:.4f}" in words
    on_medians, on_all = fit_linear(*median_by_answer(trust, reliance)), fit_linear(trust, reliance)
    assert shown["reliance"]["medians"]["slope"] == pytest.approx(on_medians.slope, rel=1e-12)
    assert shown["reliance"]["all"]["intercept"] == pytest.approx(on_all.intercept, rel=1e-12)
    assert f"{on_all.slope:.3f} [{on_all.slope_ci[0]:.3f}, {on_all.slope_ci[1]:.3f}]" in words
    assert "0.0213" in words and "0.0653" in words  # the paper's SSE and RMSE beside ours


def test_policy_evaluation_report_compares_the_blocks_like_the_paper(evaluation):
    data, sim, _, files = evaluation
    names = {p.stem for p in files.figures}
    assert {"fig_cumulative_reward", "fig_schaefer"} | MODEL_FIGURES <= names
    for png in files.figures:
        assert_not_blank(png)
    page = files.html.read_text(encoding="utf-8")
    shown = key_figures(page)["comparison"]
    expected = ttest2(sim.rewards("trust_agnostic"), sim.rewards("trust_aware"))
    got = shown["reward_tests"]["trust_agnostic vs trust_aware"]["ttest2"]
    assert got["t"] == pytest.approx(expected.t, rel=1e-12) and got["p"] == pytest.approx(expected.p, rel=1e-12)
    assert f"t({expected.df:.0f}) = {expected.t:.3f}" in text(page)
    assert shown["rewards"]["trust_aware"]["median"] == pytest.approx(float(np.median(sim.rewards("trust_aware"))))


def test_schaefer_scores_and_table3_follow_the_questionnaire_scoring(evaluation):
    data, _, _, files = evaluation
    answers = defaultdict(dict)
    for row in surveys(data):
        if row["questionnaire"] == SCHAEFER_14.id:
            condition = "before" if row["context"] == "before" else row["block_name"]
            answers[(condition, row["participant_id"])][row["item"]] = float(row["value"])
    scores = defaultdict(list)
    for (condition, _), items in sorted(answers.items()):
        scores[condition].append(score(SCHAEFER_14, items))
    page = files.html.read_text(encoding="utf-8")
    shown = key_figures(page)["comparison"]["schaefer"]
    for condition, values in scores.items():
        assert shown[condition]["mean"] == pytest.approx(np.mean(values), rel=1e-12)
    expected = ttest2(scores["before"], scores["trust_aware"])
    assert shown["tests"]["before vs trust_aware"]["ttest2"]["p"] == pytest.approx(expected.p, rel=1e-12)
    words = text(page)
    assert "paper Table 3" in words and "14. provide feedback" in words
    assert f"{np.mean(scores['trust_agnostic']):.2f}" in words
    assert "Shelf-survey answers per block (paper Table 4)" in words


def test_a_given_model_is_reported_without_inventing_standard_errors(estimation, tmp_path):
    data = estimation[0]
    report = build_report(data, model="paper")
    page = report.inline_html()
    figures = key_figures(page)
    assert figures["model"]["fitted_here"] is False
    assert figures["model"]["status_counts"] == {"given": 21}
    rows = re.findall(r"<tr><td>(P\(.*?)</td><td class=num>(.*?)</td><td(?: class=num)?>(.*?)</td>", page)
    assert rows and all(se == "—" for _, _, se in rows)
    expected = solve_belief_mdp(paper_params(), p_high=30 / 71).thresholds[Complexity.HIGH]
    assert figures["policy"]["threshold"]["high"] == pytest.approx(expected)


def test_inline_page_has_every_figure_as_data_and_a_matching_csp(evaluation):
    _, _, report, files = evaluation
    page = report.inline_html()
    sources = re.findall(r"<img src='([^']+)'", page)
    assert len(sources) == len(files.figures) and all(s.startswith("data:image/png;base64,") for s in sources)
    for src, png in zip(sources, report.figures(), strict=True):
        assert base64.b64decode(src.split(",", 1)[1]) == png.png
    digest = base64.b64encode(hashlib.sha256(STYLE.encode()).digest()).decode()
    assert f"'sha256-{digest}'" in content_security_policy() and f"<style>{STYLE}</style>" in page
    assert "<script>" not in page and "src='figures/" not in page


def test_no_model_data_is_a_clear_data_error(tmp_path):
    write_simulated_export(tmp_path / "excluded", "demo", 2, excluded=("sim-0001", "sim-0002"))
    with pytest.raises(DataError, match="no trials left after removing practice and excluded rows"):
        build_report(tmp_path / "excluded")
    (tmp_path / "empty").mkdir()
    header = (tmp_path / "excluded" / "trials.csv").read_text().splitlines()[0]
    (tmp_path / "empty" / "trials.csv").write_text(header + "\n")
    with pytest.raises(DataError, match="no trials left"):
        build_report(tmp_path / "empty")
    with pytest.raises(DataError, match="not a directory"):
        build_report(tmp_path / "nowhere")


def test_trials_alone_give_a_report_that_says_what_is_missing(tmp_path):
    write_simulated_export(tmp_path, "demo", 1)
    (tmp_path / "surveys.csv").unlink()
    (tmp_path / "participants.csv").unlink()
    report = build_report(tmp_path, restarts=1)
    files = report.write(tmp_path / "out")
    words = text(files.html.read_text(encoding="utf-8"))
    assert "No participants.csv in the export" in words
    assert "No surveys.csv in the export: the shelf-survey analyses need it." in words
    assert "The policy cannot be computed from this model" in words  # 12 trials exercise too little
    assert {p.stem for p in files.figures} >= MODEL_FIGURES
    for png in files.figures:
        assert_not_blank(png)


def test_the_blank_check_rejects_a_figure_without_data(tmp_path):
    fig, axes = new_figure(8, 4)
    axes[0].set(title="A title", xlabel="x (units)", ylabel="y (units)")
    (tmp_path / "empty.png").write_bytes(to_png(fig))
    with pytest.raises(AssertionError, match="shows no data"):
        assert_not_blank(tmp_path / "empty.png")
