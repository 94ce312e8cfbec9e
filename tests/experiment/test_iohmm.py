import json
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from experiment.iohmm import (
    N_PARAMETERS,
    IOHMMParams,
    ModelError,
    filter_beliefs,
    model_document,
    paper_params,
    params_from_document,
    update_belief,
)
from experiment.task import Complexity as C
from experiment.task import Experience as E
from experiment.task import HumanAction as O
from experiment.task import RobotAction as A

probabilities = st.floats(0.0, 1.0, allow_nan=False)
param_vectors = st.lists(probabilities, min_size=N_PARAMETERS, max_size=N_PARAMETERS).map(np.array)
trials = st.tuples(st.sampled_from(list(C)), st.sampled_from(list(A)), st.sampled_from(list(O)),
                   st.sampled_from(list(E)))


def test_paper_parameters():
    p = paper_params()
    assert p.initial_high == 0.82
    assert p.p_high_after(C.HIGH, A.ASK, E.POSITIVE).tolist() == [0.13, 1.0]
    assert p.p_observation(C.HIGH, A.AUTO, O.RELY) == pytest.approx([0.43, 0.94])
    assert p.p_observation(C.LOW, A.ASK, O.INTERVENE).tolist() == [1.0, 1.0]
    assert math.isnan(p.p_high_after(C.LOW, A.ASK, E.POSITIVE)[0])  # cannot occur, not estimated


def test_model_json_round_trip():
    doc = json.loads(json.dumps(model_document(paper_params(), loglik=-1.5)))
    assert doc["params"]["transitions"]["high"]["auto"]["negative"] == {"from_low": 0.12, "from_high": 0.67}
    assert doc["params"]["emissions"]["high"]["auto"] == {"p_rely_low": 0.43, "p_rely_high": 0.94}
    assert np.array_equal(params_from_document(doc).to_vector(), paper_params().to_vector(), equal_nan=True)


@pytest.mark.parametrize(("doc", "message"), [
    ({"format": "x"}, "not a trustlab model"),
    ({"format": "trustlab-iohmm", "version": 99, "params": {}}, "unsupported model version"),
    ({"format": "trustlab-iohmm", "version": 1, "params": {"initial": {"p_high": 0.5}}}, "is missing"),
])
def test_bad_model_documents_say_what_is_wrong(doc, message):
    with pytest.raises(ModelError, match=message):
        params_from_document(doc)


def test_out_of_range_probability_is_rejected():
    vector = paper_params().to_vector()
    vector[3] = 1.5
    with pytest.raises(ModelError, match="outside"):
        IOHMMParams.from_vector(vector)


@given(vector=param_vectors, sequence=st.lists(trials, max_size=30), method=st.sampled_from(["bayes", "paper"]))
def test_beliefs_stay_probabilities(vector, sequence, method):
    params = IOHMMParams.from_vector(vector)
    sequence = [t for t in sequence if not (t[1] == A.ASK and t[2] == O.RELY)]
    try:
        beliefs = filter_beliefs(params, sequence, method)
    except ModelError:
        return  # an observation the model gives probability 0
    assert ((beliefs >= 0) & (beliefs <= 1)).all()


def test_bayes_filter_learns_from_the_human_action_and_paper_update_does_not():
    p = paper_params()
    rely = update_belief(p, 0.5, C.HIGH, A.AUTO, O.RELY, E.POSITIVE, "bayes")
    paper = update_belief(p, 0.5, C.HIGH, A.AUTO, O.RELY, E.POSITIVE, "paper")
    assert paper == pytest.approx(0.5 * 1.0 + 0.5 * 0.64)
    post = 0.5 * 0.94 / (0.5 * 0.94 + 0.5 * 0.43)
    assert rely == pytest.approx(post * 1.0 + (1 - post) * 0.64)
    # asking carries no information about trust, so the two agree
    assert update_belief(p, 0.3, C.HIGH, A.ASK, O.INTERVENE, E.POSITIVE, "bayes") == pytest.approx(
        update_belief(p, 0.3, C.HIGH, A.ASK, O.INTERVENE, E.POSITIVE, "paper"))


def test_an_action_the_model_calls_impossible_is_not_conditioned_on():
    """Boundary estimates (here P(trust high) = 1 and P(rely | high trust) = 1) must not stop a running study."""
    vector = paper_params().to_vector()
    vector[0] = 1.0
    params = IOHMMParams.from_vector(vector)
    assert params.p_intervene(C.LOW, A.AUTO)[1] == 0.0
    bayes = update_belief(params, 1.0, C.LOW, A.AUTO, O.INTERVENE, E.NEGATIVE, "bayes")
    assert bayes == update_belief(params, 1.0, C.LOW, A.AUTO, O.INTERVENE, E.NEGATIVE, "paper")
    with pytest.raises(ModelError, match="cannot rely"):
        update_belief(params, 0.5, C.LOW, A.ASK, O.RELY, E.NEGATIVE, "bayes")

