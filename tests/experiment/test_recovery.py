import json
import math
from dataclasses import replace

import numpy as np
import pytest

from experiment.iohmm import PARAMETER_NAMES, paper_params
from experiment.recovery import recover, sequence_of, summarise, verdict
from experiment.simulate import simulate_study
from experiment.templates import template


def test_the_figures_of_one_parameter():
    estimates, stderrs = np.array([0.5, 0.7, 0.62, 0.0]), np.array([0.1, 0.05, 0.02, math.nan])
    figures = summarise("p", 0.6, estimates, stderrs, ["estimated", "estimated", "estimated", "boundary"], 4)
    errors = estimates - 0.6
    assert figures.bias == pytest.approx(errors.mean()) and figures.rmse == pytest.approx(np.sqrt((errors ** 2).mean()))
    # 0.5 ± 0.196 holds 0.6; 0.7 ± 0.098 does not; 0.62 ± 0.039 does
    assert figures.coverage == pytest.approx(2 / 3) and figures.mean_stderr == pytest.approx(np.mean([0.1, 0.05, 0.02]))
    assert (figures.n_exercised, figures.n_estimated, figures.n_boundary) == (4, 3, 1)
    assert figures.verdict == "intervals off" and figures.identified  # intervals in most studies, but off


def test_the_verdicts():
    assert verdict(19, 1, 0.95, 20) == "recovered"
    assert verdict(19, 1, 0.80, 20) == "intervals off"
    assert verdict(3, 17, math.nan, 20) == "at a bound"
    assert verdict(3, 2, 0.9, 20) == "not identified"


def test_a_sequence_leaves_the_practice_trials_out():
    sim = simulate_study(template("demo-fast"), paper_params(), 1, seed=0)
    [participant] = sim.participants
    records = [replace(r, practice=True) if i < 2 else r for i, r in enumerate(participant.records)]
    seq = sequence_of(records)
    assert len(seq) == len(records) - 2
    assert seq.human_action.tolist() == [r.human_action.code for r in records[2:]]


def test_a_recovery_run_of_the_paper_model_repeats_and_flags_what_sits_at_a_bound():
    config = template("model-estimation")
    result = recover(config, paper_params(), 8, 3, seed=1, restarts=3)
    true = paper_params().to_vector()
    assert [p.name for p in result.parameters] == [n for n, v in zip(PARAMETER_NAMES, true, strict=True)
                                                   if not math.isnan(v)]
    by_name = {p.name: p for p in result.parameters}
    # the paper's P(rely | high trust, low complexity) is 1: its estimates sit at the bound, no interval
    assert by_name["emissions.low.auto.p_rely_high"].verdict == "at a bound"
    assert "emissions.low.auto.p_rely_high" in result.not_identified()
    for p in result.parameters:
        assert p.n_exercised <= 3 and p.n_estimated + p.n_boundary + p.n_unidentified <= 3
        assert math.isnan(p.coverage) or 0.0 <= p.coverage <= 1.0
    again = recover(config, paper_params(), 8, 3, seed=1, restarts=3)
    assert json.dumps(again.to_dict()) == json.dumps(result.to_dict())
    with pytest.raises(ValueError, match="2 replications"):
        recover(config, paper_params(), 8, 1)
