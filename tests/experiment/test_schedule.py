import os
import subprocess
import sys
from collections import Counter
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from experiment import defaults
from experiment.schedule import (
    STUDY1_SCHEDULE,
    STUDY2_BLOCK_SCHEDULE,
    BernoulliSchedule,
    CountsSchedule,
    assign_block_order,
    block_orders,
    complexity_schedule,
    derive_rng,
    is_shelf_end,
    n_shelves,
    parse_schedule,
    shelves,
)
from experiment.task import Complexity as C

P_ABANDON = 0.3
seeds = st.integers(0, 2**63 - 1)
specs = st.one_of(
    st.builds(BernoulliSchedule, n_trials=st.integers(1, 200), p_high=st.floats(0.0, 1.0)),
    st.builds(CountsSchedule, n_low=st.integers(0, 100), n_high=st.integers(1, 100)),
)


# --- schedules ----------------------------------------------------------------------

@given(spec=specs, seed=seeds)
def test_same_seed_same_schedule(spec, seed):
    first = complexity_schedule(spec, derive_rng(seed, "p1", 0, "complexity"))
    assert first == complexity_schedule(spec, derive_rng(seed, "p1", 0, "complexity"))
    assert len(first) == spec.n_trials


@given(n_low=st.integers(0, 80), n_high=st.integers(0, 80), seed=seeds)
def test_counts_schedule_has_exact_counts(n_low, n_high, seed):
    assume(n_low + n_high > 0)
    schedule = complexity_schedule(CountsSchedule(n_low=n_low, n_high=n_high), np.random.default_rng(seed))
    assert Counter(schedule) == Counter({C.LOW: n_low, C.HIGH: n_high}) - Counter()


def test_counts_schedule_is_shuffled_and_paper_designs():
    rng = np.random.default_rng(0)
    assert STUDY1_SCHEDULE.n_trials == defaults.STUDY1_TRIALS_LOW + defaults.STUDY1_TRIALS_HIGH
    assert STUDY2_BLOCK_SCHEDULE.n_trials == (defaults.STUDY2_TRIALS_LOW_PER_BLOCK
                                              + defaults.STUDY2_TRIALS_HIGH_PER_BLOCK)
    orders = {tuple(complexity_schedule(STUDY2_BLOCK_SCHEDULE, rng)) for _ in range(20)}
    assert len(orders) == 20


@pytest.mark.parametrize(("p_high", "expected"), [(0.0, C.LOW), (1.0, C.HIGH)])
def test_bernoulli_extremes(p_high, expected):
    spec = BernoulliSchedule(n_trials=50, p_high=p_high)
    assert set(complexity_schedule(spec, np.random.default_rng(1))) == {expected}


def test_bernoulli_frequency():
    schedule = complexity_schedule(BernoulliSchedule(n_trials=20_000, p_high=0.25), np.random.default_rng(2))
    assert schedule.count(C.HIGH) / len(schedule) == pytest.approx(0.25, abs=0.015)


def test_parse_schedule_discriminates_on_kind():
    assert parse_schedule({"kind": "bernoulli", "n_trials": 10, "p_high": 0.5}) == BernoulliSchedule(n_trials=10,
                                                                                                     p_high=0.5)
    assert parse_schedule({"kind": "counts", "n_low": 3, "n_high": 4}).n_trials == 7


@pytest.mark.parametrize(("doc", "message"), [
    ({"kind": "bernoulli", "n_trials": 0, "p_high": 0.5}, "greater than or equal to 1"),
    ({"kind": "bernoulli", "n_trials": 5, "p_high": 1.5}, "less than or equal to 1"),
    ({"kind": "bernoulli", "n_trials": 5, "p_high": -0.1}, "greater than or equal to 0"),
    ({"kind": "counts", "n_low": 0, "n_high": 0}, "at least one trial"),
    ({"kind": "counts", "n_low": -1, "n_high": 3}, "greater than or equal to 0"),
    ({"kind": "counts", "n_low": 1, "n_high": 3, "p_high": 0.5}, "Extra inputs are not permitted"),
    ({"kind": "weekly", "n_trials": 3}, "does not match any of the expected tags"),
    ({"n_trials": 3, "p_high": 0.5}, "Unable to extract tag"),
])
def test_invalid_schedules_say_what_is_wrong(doc, message):
    with pytest.raises(ValidationError, match=message):
        parse_schedule(doc)


def test_specs_are_frozen():
    with pytest.raises(ValidationError):
        STUDY1_SCHEDULE.n_low = 3


# --- random streams --------------------------------------------------------------------

def test_derive_rng_streams_agree_and_differ_by_key():
    def draw(*keys):
        return derive_rng(7, *keys).random(4).tolist()

    assert draw("p1", 0, "complexity") == draw("p1", 0, "complexity")
    variants = [draw("p1", 0, "complexity"), draw("p1", 1, "complexity"), draw("p2", 0, "complexity"),
                draw("p1", 0, "outcome"), draw("p1", "0", "complexity"), draw("p1", 0), draw()]
    assert len({tuple(v) for v in variants}) == len(variants)
    assert derive_rng(8, "p1").random() != derive_rng(7, "p1").random()


def test_derive_rng_is_stable_across_processes():
    code = "from experiment.schedule import derive_rng; print(derive_rng(11, 'p9', 2, 'outcome').integers(1 << 62))"
    outputs = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                              env=os.environ | {"PYTHONHASHSEED": str(h)}, cwd=Path(__file__).parents[2]).stdout
               for h in (1, 2)}
    assert outputs == {f"{derive_rng(11, 'p9', 2, 'outcome').integers(1 << 62)}\n"}


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_derive_rng_rejects_bad_seeds(seed):
    with pytest.raises(ValueError, match="non-negative integer"):
        derive_rng(seed)


def test_derive_rng_rejects_bad_keys():
    with pytest.raises(TypeError, match="str or int"):
        derive_rng(1, 2.5)


# --- shelves ---------------------------------------------------------------------------

def test_shelves_last_one_shorter():
    assert shelves(7, 3) == [1, 1, 1, 2, 2, 2, 3]
    assert n_shelves(7, 3) == 3
    assert [is_shelf_end(i, 7, 3) for i in range(7)] == [False, False, True, False, False, True, True]


@given(n_trials=st.integers(0, 300), shelf_size=st.integers(1, 50))
def test_shelf_ends_close_each_shelf(n_trials, shelf_size):
    numbers = shelves(n_trials, shelf_size)
    ends = [i for i in range(n_trials) if is_shelf_end(i, n_trials, shelf_size)]
    assert len(ends) == n_shelves(n_trials, shelf_size) == len(set(numbers))
    assert all(numbers[i] != numbers[i + 1] for i in ends[:-1])
    assert all(count <= shelf_size for count in Counter(numbers).values())


@pytest.mark.parametrize(("args", "message"), [((5, 0), "shelf_size"), ((-1, 3), "n_trials")])
def test_shelves_reject_bad_arguments(args, message):
    with pytest.raises(ValueError, match=message):
        shelves(*args)
    with pytest.raises(ValueError, match="trial_index"):
        is_shelf_end(5, 5, 2)


# --- block orders ------------------------------------------------------------------------

def test_all_orders():
    assert block_orders(2) == [(0, 1), (1, 0)]
    assert len(block_orders(4, "all")) == 24


@pytest.mark.parametrize("n", range(1, 10))
def test_latin_square_rows_and_columns(n):
    square = block_orders(n, "latin")
    assert len(square) == n
    assert all(sorted(row) == list(range(n)) for row in square)
    assert all(sorted(column) == list(range(n)) for column in zip(*square, strict=True))


@pytest.mark.parametrize("n", [2, 4, 6, 8, 10])
def test_williams_carryover_balance_for_even_n(n):
    successions = Counter(pair for row in block_orders(n, "latin") for pair in pairwise(row))
    assert set(successions) == {(a, b) for a in range(n) for b in range(n) if a != b}
    assert set(successions.values()) == {1}


def test_block_orders_reject_bad_arguments():
    with pytest.raises(ValueError, match="n_blocks"):
        block_orders(0)
    with pytest.raises(ValueError, match="too many"):
        block_orders(9, "all")
    with pytest.raises(ValueError, match="unknown method"):
        block_orders(3, "random")


# --- assignment --------------------------------------------------------------------------

def spread(counts):
    return max(counts.values()) - min(counts.values())


order_sets = st.sampled_from([block_orders(2), block_orders(3), block_orders(4, "latin"), block_orders(3, "latin")])


@given(orders=order_sets, data=st.data(), seed=seeds)
def test_assignment_takes_a_least_used_order(orders, data, seed):
    counts = {o: data.draw(st.integers(0, 6)) for o in orders}
    assignment = assign_block_order(orders, counts, np.random.default_rng(seed))
    fewest = min(counts.values())
    assert counts[assignment.order] == fewest
    assert set(assignment.tied_orders) == {o for o in orders if counts[o] == fewest}
    assert dict(assignment.counts_before) == counts
    after = counts | {assignment.order: counts[assignment.order] + 1}
    assert spread(after) <= max(spread(counts), 1)  # assignment never widens an imbalance
    assert "assigned" in assignment.audit_line()


def test_ties_are_broken_uniformly():
    orders = block_orders(3)
    rng = np.random.default_rng(3)
    chosen = Counter(assign_block_order(orders, {}, rng).order for _ in range(6000))
    assert set(chosen) == set(orders)
    assert all(abs(n - 1000) < 150 for n in chosen.values())


def test_no_dropouts_gives_exact_halves():
    orders, counts, rng = block_orders(2), Counter(), np.random.default_rng(4)
    for _ in range(defaults.STUDY2_PARTICIPANTS):
        counts[assign_block_order(orders, counts, rng).order] += 1
    assert set(counts.values()) == {defaults.STUDY2_PARTICIPANTS // 2}


def test_orders_may_be_block_names():
    orders = [("aware", "agnostic"), ("agnostic", "aware")]
    assignment = assign_block_order(orders, {("aware", "agnostic"): 3}, np.random.default_rng(0))
    assert assignment.order == ("agnostic", "aware") and assignment.tied_orders == (("agnostic", "aware"),)
    assert "agnostic-aware" in assignment.audit_line()


def test_assignment_rejects_inconsistent_input():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="not candidates"):
        assign_block_order(block_orders(2), {(0, 2): 1}, rng)
    with pytest.raises(ValueError, match="≥ 0"):
        assign_block_order(block_orders(2), {(0, 1): -1}, rng)
    with pytest.raises(ValueError, match="distinct"):
        assign_block_order([(0, 1), (0, 1)], {}, rng)
    with pytest.raises(ValueError, match="at least one"):
        assign_block_order([], {}, rng)


@settings(max_examples=60)
@given(orders=order_sets, seed=seeds, n=st.integers(1, 200))
def test_sequential_dropouts_stay_balanced(orders, seed, n):
    """Participants one at a time, each abandoning with probability 0.3 before the next arrives.

    With at most one drop-out between assignments, the active counts differ by
    at most 1 right after every assignment (a drop-out makes its order the unique
    minimum, which the next assignment refills) and by at most 2 at any moment;
    at the end, the completed counts (= active counts) differ by at most 2.
    """
    rng, active = np.random.default_rng(seed), dict.fromkeys(orders, 0)
    for _ in range(n):
        order = assign_block_order(orders, active, rng).order
        active[order] += 1
        assert spread(active) <= 1
        if rng.random() < P_ABANDON:
            active[order] -= 1
        assert spread(active) <= 2
    assert spread(active) <= 2


def simulate_overlapping(orders, rng, n_arrivals, max_in_flight):
    """Arrivals and departures interleaved at random; yields (event, active, completed, dropouts_since_balanced)."""
    active, completed = dict.fromkeys(orders, 0), dict.fromkeys(orders, 0)
    in_flight, arrived, since_balanced = [], 0, 0
    while arrived < n_arrivals or in_flight:
        if arrived < n_arrivals and len(in_flight) < max_in_flight and (not in_flight or rng.random() < 0.5):
            before = dict(active)
            order = assign_block_order(orders, active, rng).order
            active[order] += 1
            in_flight.append(order)
            arrived += 1
            assert spread(active) <= max(spread(before), 1)
        else:
            order = in_flight.pop(int(rng.integers(len(in_flight))))
            if rng.random() < P_ABANDON:
                active[order] -= 1
                since_balanced += 1
            else:
                completed[order] += 1
        since_balanced = 0 if spread(active) <= 1 else since_balanced
        # Only drop-outs widen the imbalance, by 1 each; assignments never do.
        assert spread(active) <= 1 + since_balanced
    return active, completed


@settings(max_examples=40)
@given(orders=order_sets, seed=seeds, n=st.integers(1, 150), max_in_flight=st.integers(1, 10))
def test_overlapping_dropouts_only_widen_by_dropouts(orders, seed, n, max_in_flight):
    active, completed = simulate_overlapping(orders, np.random.default_rng(seed), n, max_in_flight)
    assert active == completed  # once everyone has left, active means completed


@pytest.mark.parametrize("seed", range(5))
def test_long_run_completed_counts_end_balanced(seed):
    _, completed = simulate_overlapping(block_orders(2), np.random.default_rng(seed), 2000, 10)
    assert spread(completed) <= 0.01 * sum(completed.values())
