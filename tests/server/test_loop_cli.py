"""The whole loop through the command line, as an experimenter without the dashboard runs it (issue 5):
an estimation study run by bots → ``export`` → ``fit`` → ``deploy`` → bots on the evaluation study → ``report``.
"""

from __future__ import annotations

import csv
import json

from typer.testing import CliRunner

from experiment.config import RandomAssistSpec
from experiment.provenance import content_hash
from experiment.schedule import CountsSchedule
from experiment.task import TaskParams
from experiment.templates import demo_fast, model_estimation
from server.cli import app
from server.harness.live import live_server

runner = CliRunner()
ESTIMATION_TRIALS = (8, 8)  # low, high
EVALUATION_TRIALS = 12  # demo-fast: two blocks of 6
ESTIMATION_BOTS, EVALUATION_BOTS = 6, 4


def trustlab(*args) -> str:
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, f"trustlab {' '.join(map(str, args))}: {result.output}"
    return result.output


def estimation_config() -> dict:
    """Paper study 1 at machine pace, shortened; the robot asks often and fails often, so that a few bots
    exercise every input of the model the trust-aware policy needs."""
    config = model_estimation()
    block = config.blocks[0].model_copy(update={
        "schedule": CountsSchedule(n_low=ESTIMATION_TRIALS[0], n_high=ESTIMATION_TRIALS[1]),
        "policy": RandomAssistSpec(p_ask_low=0.4, p_ask_high=0.4)})
    return config.model_copy(update={"blocks": [block], "timing": demo_fast().timing,
                                     "task": TaskParams(p_success_low=0.6, p_success_high=0.5)}).model_dump(mode="json")


def test_estimation_fit_deploy_evaluate_report_through_the_cli(tmp_path):
    database_url = f"sqlite:///{tmp_path / 'loop.db'}"
    trustlab("migrate", "--database-url", database_url)
    with live_server(database_url) as live:
        response = live.admin("POST", "/api/admin/studies",
                              json={"status": "open", "slug": "estimation", "config": estimation_config()})
        assert response.status_code == 201, response.text
        # All the bots at once: a bot mostly waits (its scripted teleoperations are paced by the robot), so together
        # they take about the same CPU in two thirds of the time.
        trustlab("bots", live.url, "--study", "estimation", "--participants", ESTIMATION_BOTS,
                 "--concurrency", ESTIMATION_BOTS, "--seed", 4)
        trustlab("export", "estimation", "--out", tmp_path / "estimation", "--database-url", database_url)
        fitted = json.loads(trustlab("fit", tmp_path / "estimation" / "trials.csv", "--out", tmp_path / "model.json",
                                     "--restarts", 4, "--json"))
        assert fitted["fitted_on"]["participants"] and len(fitted["params"]) > 0
        deployed = json.loads(trustlab("deploy", tmp_path / "model.json", "--trials",
                                       tmp_path / "estimation" / "trials.csv",
                                       "--slug", "evaluation", "--template", "demo-fast", "--database-url",
                                       database_url,
                                       "--open", "--json"))
        assert deployed["slug"] == "evaluation"
        trustlab("bots", live.url, "--study", "evaluation", "--participants", EVALUATION_BOTS,
                 "--concurrency", EVALUATION_BOTS, "--seed", 5)
    report = json.loads(trustlab("report", "evaluation", "--out", tmp_path / "report", "--database-url", database_url,
                                 "--restarts", 2, "--json"))

    model_hash = content_hash(json.loads((tmp_path / "model.json").read_text()))
    with open(tmp_path / "report" / "data" / "trials.csv", encoding="utf-8") as handle:
        rows = [r for r in csv.DictReader(handle) if r["practice"] == "0"]
    assert len(rows) == EVALUATION_BOTS * EVALUATION_TRIALS
    aware = [r for r in rows if r["policy"] == "trust_aware"]
    assert aware and {r["model_hash"] for r in aware} == {model_hash}  # the evaluation ran under the fitted model
    assert {r["policy"] for r in rows} == {"trust_aware", "trust_agnostic"}
    html = (tmp_path / "report" / "report.html").read_text(encoding="utf-8")
    figures = sorted((tmp_path / "report" / "figures").glob("*.png"))
    assert len(figures) >= 5 and all(f.name in html for f in figures)
    assert report["report"].endswith("report.html") and len(report["figures"]) == len(figures)
