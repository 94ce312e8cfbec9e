"""The study's duration, estimated from its configuration for the consent and instructions pages."""

from __future__ import annotations

import pytest

from experiment import defaults
from experiment.config import (
    AlwaysAskSpec,
    AlwaysAutoSpec,
    BlockConfig,
    PracticeConfig,
    TimingConfig,
    TrustAgnosticSpec,
    block_label,
)
from experiment.duration import QUICK, SLOW, DurationEstimate, ask_share, attempt_s, estimate_duration, study_seconds
from experiment.schedule import CountsSchedule
from experiment.task import Complexity
from experiment.templates import TEMPLATES, demo, model_estimation, policy_evaluation
from experiment.world.trial import trial_attempt


def test_the_demo_is_not_five_minutes_and_the_paper_studies_take_longer():
    assert estimate_duration(demo()) == DurationEstimate(10, 20)
    assert estimate_duration(demo()).text == "about 10–20 minutes"
    assert estimate_duration(model_estimation()).low_minutes > estimate_duration(demo()).high_minutes
    assert estimate_duration(policy_evaluation()) == DurationEstimate(35, 60)  # (160 "Next item" pauses of 2 s)


@pytest.mark.parametrize("name", TEMPLATES)
def test_the_quick_participant_is_quicker_and_templates_say_nothing_false_about_time(name):
    config = TEMPLATES[name]()
    assert study_seconds(config, QUICK) < study_seconds(config, SLOW)
    assert "minute" not in config.description and "five" not in config.description


def test_more_trials_slower_pacing_and_more_questions_take_longer():
    base = demo()
    longer_blocks = [b.model_copy(update={"schedule": CountsSchedule(n_low=10, n_high=10)}) for b in base.blocks]
    slower = base.model_copy(update={"timing": TimingConfig(decision_window_s=8.0)})
    paused = base.model_copy(update={"timing": TimingConfig(next_item_pause_s=5.0)})
    surveyed = base.model_copy(update={"shelf_size": 1})
    for changed in (base.model_copy(update={"blocks": longer_blocks}), slower, paused, surveyed):
        for side in (QUICK, SLOW):
            assert study_seconds(changed, side) > study_seconds(base, side)
    faster = base.model_copy(update={"timing": TimingConfig(animation_speed=10.0)})
    assert study_seconds(faster, QUICK) < study_seconds(base, QUICK)
    no_practice = base.model_copy(update={"practice": PracticeConfig(enabled=False)})
    assert study_seconds(base, SLOW) - study_seconds(no_practice, SLOW) >= defaults.TUTORIAL_TELEOP_S[SLOW]


def test_a_robot_that_always_asks_costs_a_teleoperation_per_trial():
    schedule = CountsSchedule(n_low=5, n_high=5)
    ask = demo().model_copy(update={"blocks": [BlockConfig(name="b", policy=AlwaysAskSpec(), schedule=schedule)],
                                    "shelf_questionnaire": None})
    auto = ask.model_copy(update={"blocks": [BlockConfig(name="b", policy=AlwaysAutoSpec(), schedule=schedule)]})
    window, teleop = ask.timing.decision_window_s, defaults.TELEOP_PERSON_S[SLOW]
    # The slow participant intervenes in auto trials as the paper's low-trust participants: 3 % low, 57 % high.
    auto_low = 0.03 * (window / 2 + teleop) + 0.97 * (window + attempt_s(Complexity.LOW))
    auto_high = 0.57 * (window / 2 + teleop) + 0.43 * (window + attempt_s(Complexity.HIGH))
    expected = 5 * (teleop - auto_low) + 5 * (teleop - auto_high)
    assert study_seconds(ask, SLOW) - study_seconds(auto, SLOW) == pytest.approx(expected)


def test_ask_shares_follow_the_policy():
    schedule = CountsSchedule(n_low=1, n_high=1)
    config = demo()
    agnostic = BlockConfig(name="a", policy=TrustAgnosticSpec(), schedule=schedule)  # paper rates: never ask
    forced = BlockConfig(name="f", policy=TrustAgnosticSpec(actions={"low": "auto", "high": "ask"}), schedule=schedule)
    aware = config.blocks[0]
    assert [ask_share(agnostic, config, c, SLOW) for c in Complexity] == [0.0, 0.0]
    assert [ask_share(forced, config, c, QUICK) for c in Complexity] == [0.0, 1.0]
    assert [ask_share(aware, config, c, side) for c in Complexity for side in (QUICK, SLOW)] == [0, 0, 0, 1]


def test_the_attempt_time_is_the_planners():
    for complexity in Complexity:
        planned = trial_attempt(0, "someone", "block", 3, complexity.value, True).duration
        assert attempt_s(complexity) == pytest.approx(planned)


def test_block_labels_go_by_position():
    assert [block_label("Robot {letter}", i) for i in (1, 2, 26, 27)] == ["Robot A", "Robot B", "Robot Z", "Robot AA"]
    assert block_label("Part {number}", 3) == "Part 3"
