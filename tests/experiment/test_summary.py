"""The study summary a researcher checks before launch (experiment.summary)."""

from experiment.config import (
    AlwaysAskSpec,
    AlwaysAutoSpec,
    BlockConfig,
    CompensationConfig,
    RandomAssistSpec,
    TrustAgnosticSpec,
)
from experiment.duration import estimate_duration
from experiment.schedule import BernoulliSchedule, CountsSchedule
from experiment.summary import payment_words, summarize
from experiment.task import Complexity, RobotAction
from experiment.templates import demo, model_estimation, policy_evaluation


def test_policy_evaluation_in_words():
    config = policy_evaluation()
    summary = summarize(config)
    assert [(b.name, b.trials, b.n_low, b.n_high, b.shelves) for b in summary.blocks] == [
        ("trust_aware", 40, 20, 20, 5), ("trust_agnostic", 40, 20, 20, 5)]
    assert summary.scored_trials == 80 and summary.practice_trials == 4
    assert summary.blocks[0].policy == ("trust-aware: asks in high complexity when the belief of high trust ≤ 0.69; "
                                        "never asks in low complexity")
    assert summary.blocks[1].policy.startswith("trust-agnostic (intervention rates 0.006 low, 0.1848 high): never "
                                               "asks (expected reward acting alone 2.77 low, 1.02 high; asking 1)")
    assert summary.orders == [["trust_aware", "trust_agnostic"], ["trust_agnostic", "trust_aware"]]
    estimate = estimate_duration(config)
    assert (summary.duration, summary.duration_low_minutes) == (estimate.text, estimate.low_minutes)
    uses = {q.id: q.when for q in summary.questionnaires}
    assert uses == {"schaefer_14": "before the first block; after block trust_aware; after block trust_agnostic",
                    "shelf_trust_reliance": "after each shelf of 8 trials"}
    assert summary.payment == "nothing (the recruitment site pays)"


def test_other_policies_schedules_and_orders():
    blocks = [
        BlockConfig(name="r", policy=RandomAssistSpec(p_ask_low=0.1, p_ask_high=0.33),
                    schedule=BernoulliSchedule(n_trials=10, p_high=0.3)),
        BlockConfig(name="g", policy=TrustAgnosticSpec(actions={Complexity.LOW: RobotAction.AUTO,
                                                                Complexity.HIGH: RobotAction.ASK}),
                    schedule=CountsSchedule(n_low=2, n_high=1)),
        BlockConfig(name="auto", policy=AlwaysAutoSpec(), schedule=CountsSchedule(n_low=1, n_high=0)),
        BlockConfig(name="ask", policy=AlwaysAskSpec(), schedule=CountsSchedule(n_low=1, n_high=0)),
    ]
    config = demo().model_copy(update={"blocks": blocks, "counterbalance": "latin", "practice":
                                       demo().practice.model_copy(update={"enabled": False})})
    summary = summarize(config)
    assert [b.policy for b in summary.blocks] == [
        "random: asks with probability 0.1 in low and 0.33 in high complexity",
        "trust-agnostic (actions given): acts alone in low and asks in high",
        "always acts alone: never asks for help", "always asks for help"]
    assert summary.blocks[0].n_high == 3 and "probability 0.3" in summary.blocks[0].schedule
    assert summary.scored_trials == 15 and summary.practice_trials == 0
    assert len(summary.orders) == 4 and all(sorted(o) == sorted(b.name for b in blocks) for o in summary.orders)
    assert "Latin square" in summary.counterbalance


def test_one_block_has_one_order_and_pay_in_words():
    summary = summarize(model_estimation())
    assert summary.orders == [["estimation"]] and summary.payment == "15.00 USD for taking part"
    pay = CompensationConfig(currency="GBP", base=2, bonus_per_point=0.05, bonus_cap=3)
    assert payment_words(pay) == ("2.00 GBP for taking part + 0.05 GBP per point of the final score, up to 3.00 GBP "
                                  "(at most 5.00 GBP)")
    assert payment_words(CompensationConfig(bonus_per_point=0.1, bonus_cap=1)) == (
        "0.10 USD per point of the final score, up to 1.00 USD")
    assert payment_words(CompensationConfig(bonus_per_point=0.1)) == "nothing (the recruitment site pays)"


def test_the_amount_paid_follows_the_rule_the_summary_describes():
    pay = CompensationConfig(currency="GBP", base=2, bonus_per_point=0.05, bonus_cap=3)
    assert (pay.amount(-10), pay.amount(0), pay.amount(21), pay.amount(1000)) == (2.0, 2.0, 3.05, 5.0)
    assert "at most 5.00 GBP" in payment_words(pay)  # the cap the amount reaches
    nothing = CompensationConfig(bonus_per_point=0.1)  # no cap: no bonus, as the summary says
    assert nothing.amount(50) == 0.0 and not nothing.defined and not nothing.has_bonus


def test_questionnaires_at_the_end_are_in_the_summary_and_the_duration():
    from experiment.config import validate_document
    config = validate_document(policy_evaluation().model_dump(mode="json") | {"questionnaires_end": ["demographics"]})
    uses = {q.id: q.when for q in summarize(config).questionnaires}
    assert uses["demographics"] == "at the end of the study, after every block"
    from experiment import duration
    for side in (0, 1):  # the quick and the slow participant: the end page's time is counted
        assert duration._questionnaires_s(config, side) > duration._questionnaires_s(policy_evaluation(), side)
