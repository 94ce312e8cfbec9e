import json
import math
from typing import Any, cast

import numpy as np
import pytest

from experiment.iohmm import paper_params
from experiment.model_selection import Candidate, assign_folds, choose, held_out_loglik, paired_gap, select_states
from experiment.sequences import Sequence, sample_random_assist_sequences
from experiment.trust_states import KStateParams, from_iohmm, illustrative_three_state_model, sample_sequences_k
from experiment.trust_states_em import EMSettings, KStateFit, PaddedData

FAST = EMSettings(restarts=8, keep=2)


def test_the_selection_picks_three_states_on_three_state_data_and_two_on_two_state_data():
    three, _ = sample_sequences_k(illustrative_three_state_model(), 150, 60, np.random.default_rng(1000))
    selection = select_states(three, [2, 3], seed=0, settings=FAST)
    assert selection.chosen == 3, selection.reason
    assert selection.candidate(3).held_out > selection.candidate(2).held_out
    two, _ = sample_random_assist_sequences(paper_params(), 150, 60, np.random.default_rng(1000))
    selection = select_states(two, [2, 3], seed=0, settings=FAST)
    assert selection.chosen == 2, selection.reason


@pytest.fixture(scope="module")
def small_selection():
    sequences, _ = sample_random_assist_sequences(paper_params(), 30, 20, np.random.default_rng(5))
    return sequences, select_states(sequences, [3, 2], folds=3, seed=4, settings=EMSettings(restarts=4, keep=1))


def test_a_selection_records_what_it_compared_and_repeats_exactly(small_selection):
    sequences, selection = small_selection
    record = selection.to_dict()
    assert [c["n_states"] for c in record["candidates"]] == [2, 3]  # sorted
    assert record["folds"] == 3 and record["seed"] == 4 and record["n_participants"] == 30
    assert record["n_trials"] == 600 and record["bic_sample_size"] == "trials"
    assert sorted(np.bincount(record["fold_of"]).tolist()) == [10, 10, 10]
    for c in selection.candidates:
        assert len(c.fold_scores) == 3 and all(math.isfinite(s) and s < 0 for s in c.fold_scores)
        assert c.bic == pytest.approx(-2 * c.loglik + c.fit.n_free * math.log(600))
        assert c.icl == pytest.approx(c.bic + 2 * c.fit.path_entropy) and c.fit.path_entropy > 0
    again = select_states(sequences, [2, 3], folds=3, seed=4, settings=EMSettings(restarts=4, keep=1))
    assert json.dumps(again.to_dict()) == json.dumps(record)


def test_folds_are_of_whole_participants_seeded_and_balanced():
    folds = assign_folds(23, 5, seed=1)
    assert sorted(np.bincount(folds).tolist()) == [4, 4, 5, 5, 5]
    np.testing.assert_array_equal(folds, assign_folds(23, 5, seed=1))
    assert not np.array_equal(folds, assign_folds(23, 5, seed=2))
    with pytest.raises(ValueError, match="at least 5 participants"):
        assign_folds(4, 5, seed=0)
    with pytest.raises(ValueError, match="at least 2 folds"):
        assign_folds(10, 1, seed=0)


def candidate(k: int, participant_scores: np.ndarray) -> Candidate:
    return Candidate(k, cast(Any, None), (float(participant_scores.mean()) / 10,), tuple(participant_scores.tolist()))


def test_the_standard_error_rule_needs_an_extra_state_to_beat_chance():
    rng = np.random.default_rng(0)
    people = rng.normal(-4.0, 1.0, size=100)  # 100 participants of 10 trials: people differ a lot, pairing cancels it
    two = candidate(2, people)
    three_barely = candidate(3, people + 0.01 + rng.normal(0, 0.1, size=100))  # 1 SE ahead: chance
    assert choose([two, three_barely], 2.0, 1000)[0] == 2
    three_clearly = candidate(3, people + 0.1 + rng.normal(0, 0.1, size=100))  # 10 SE ahead
    chosen, reason = choose([two, three_clearly], 2.0, 1000)
    assert chosen == 3 and "beats fewer states" in reason
    four_barely = candidate(4, people + 0.11 + rng.normal(0, 0.1, size=100))
    chosen, reason = choose([two, three_clearly, four_barely], 2.0, 1000)
    assert chosen == 3 and "the fewest" in reason and "4 states" in reason
    gap, se = paired_gap(four_barely, two, 1000)
    assert gap == pytest.approx(float(np.subtract(four_barely.participant_scores, people).sum()) / 1000)
    assert se < 0.002  # the people's spread (1.0 each) is not in it


def test_a_held_out_trial_the_fit_called_impossible_costs_a_finite_amount():
    params = from_iohmm(paper_params())
    p_rely = params.p_rely.copy()
    p_rely[1, 0] = 0.0  # low trust never relies in high complexity
    fit = KStateFit(KStateParams(params.initial, params.transition, p_rely), 0.0, 2, np.zeros(1))
    relies = PaddedData([Sequence([1, 1], [0, 0], [0, 0], [1, 1])])
    [score] = held_out_loglik(fit, relies)
    assert math.isfinite(score) and score < 0


def test_every_participant_needs_a_trial_and_a_candidate_is_needed():
    sequences, _ = sample_random_assist_sequences(paper_params(), 6, 5, np.random.default_rng(0))
    with pytest.raises(ValueError, match="no candidate"):
        select_states(sequences, [], folds=2)
    with pytest.raises(ValueError, match="at least one trial"):
        select_states([*sequences, Sequence([], [], [], [])], [2], folds=2)
