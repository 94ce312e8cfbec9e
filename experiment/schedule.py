"""Seeded complexity schedules, shelves and block-order counterbalancing (SPEC §2–§3).

- A *schedule spec* says how the complexity of a block's trials is drawn:
  i.i.d. Bernoulli(``p_high``) or a fixed number of low and high trials in a
  random order (paper: study 1 = 41 low + 30 high; study 2 = 20 + 20 per block).
- ``derive_rng`` gives every (study seed, participant, block, purpose) its own
  reproducible random stream, so any participant's schedule can be rebuilt.
- Trials are grouped into *shelves* (sub-blocks); the trust and reliance
  questions follow the last trial of each shelf.
- Block orders are counterbalanced: the next participant gets the order with
  the fewest active (started and not abandoned) participants, ties broken at
  random, which keeps the design balanced when participants drop out.

All functions are pure; randomness comes in as an ``np.random.Generator``.
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from experiment import defaults
from experiment.task import Complexity

BlockOrder = tuple[int, ...]
OrderMethod = Literal["all", "latin"]

#: Largest number of blocks for which ``block_orders(n, "all")`` lists all n! orders.
MAX_BLOCKS_ALL_ORDERS = 8
#: The rule ``assign_block_order`` applies, recorded in every ``Assignment``.
ASSIGNMENT_RULE = "fewest-active, uniform random tie-break"


# --- Schedule specs ------------------------------------------------------------

_STUDY2_BLOCK_TRIALS = defaults.STUDY2_TRIALS_LOW_PER_BLOCK + defaults.STUDY2_TRIALS_HIGH_PER_BLOCK

class BernoulliSchedule(BaseModel):
    """Each trial is high complexity with probability ``p_high``, independently."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    kind: Literal["bernoulli"] = Field("bernoulli", description="Each trial's complexity drawn independently")
    # Required (no silent default), but with the paper's study-2 block as the example a form starts from.
    n_trials: int = Field(ge=1, title="Number of trials", description="number of trials in the block (N ≥ 1)",
                          examples=[_STUDY2_BLOCK_TRIALS])
    p_high: float = Field(ge=0.0, le=1.0, title="P(high complexity)",
                          description="probability that a trial is high complexity",
                          examples=[defaults.STUDY2_TRIALS_HIGH_PER_BLOCK / _STUDY2_BLOCK_TRIALS])


class CountsSchedule(BaseModel):
    """Exactly ``n_low`` low and ``n_high`` high trials, in a uniformly random order."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    kind: Literal["counts"] = Field("counts", description=(
        "A fixed number of low and high trials, shuffled (the paper's design)"))
    n_low: int = Field(ge=0, title="Low-complexity trials", description="number of low-complexity trials",
                       examples=[defaults.STUDY2_TRIALS_LOW_PER_BLOCK])
    n_high: int = Field(ge=0, title="High-complexity trials", description="number of high-complexity trials",
                        examples=[defaults.STUDY2_TRIALS_HIGH_PER_BLOCK])

    @model_validator(mode="after")
    def _at_least_one_trial(self) -> CountsSchedule:
        if self.n_low + self.n_high < 1:
            raise ValueError("a block needs at least one trial: n_low + n_high must be ≥ 1")
        return self

    @property
    def n_trials(self) -> int:
        return self.n_low + self.n_high

    @property
    def p_high(self) -> float:
        """The fraction of high-complexity trials (what a policy sees as P(C = high))."""
        return self.n_high / self.n_trials


ScheduleSpec = Annotated[BernoulliSchedule | CountsSchedule, Field(discriminator="kind")]
_SPEC_ADAPTER: TypeAdapter[BernoulliSchedule | CountsSchedule] = TypeAdapter(ScheduleSpec)

#: Paper study 1 (§4): one block of 41 low + 30 high trials.
STUDY1_SCHEDULE = CountsSchedule(n_low=defaults.STUDY1_TRIALS_LOW, n_high=defaults.STUDY1_TRIALS_HIGH)
#: Paper study 2 (§5.2): each block has 20 low + 20 high trials.
STUDY2_BLOCK_SCHEDULE = CountsSchedule(n_low=defaults.STUDY2_TRIALS_LOW_PER_BLOCK,
                                       n_high=defaults.STUDY2_TRIALS_HIGH_PER_BLOCK)


def parse_schedule(data: object) -> BernoulliSchedule | CountsSchedule:
    """Validate a schedule document such as ``{"kind": "counts", "n_low": 20, "n_high": 20}``.

    Raises ``pydantic.ValidationError`` (a ``ValueError``) saying which field is wrong.
    """
    return _SPEC_ADAPTER.validate_python(data)


def complexity_schedule(spec: BernoulliSchedule | CountsSchedule, rng: np.random.Generator) -> list[Complexity]:
    """The complexity of each trial of one block, in trial order (length ``spec.n_trials``)."""
    if isinstance(spec, BernoulliSchedule):
        high = rng.random(spec.n_trials) < spec.p_high
    else:
        high = rng.permutation(np.repeat([False, True], [spec.n_low, spec.n_high]))
    return [Complexity.HIGH if h else Complexity.LOW for h in high]


# --- Random streams ------------------------------------------------------------

def _key_word(key: str | int) -> int:
    """A stable 64-bit integer for one key; the top bit is set so that every key
    is exactly two 32-bit words of the spawn key and tuples of keys cannot alias."""
    if isinstance(key, bool) or not isinstance(key, (str, int)):
        raise TypeError(f"rng keys must be str or int, got {type(key).__name__}")
    tagged = f"{type(key).__name__}:{key}".encode()  # 1 and "1" are different keys
    digest = hashlib.blake2b(tagged, digest_size=8, person=b"trustlab-rng").digest()
    return int.from_bytes(digest, "big") | (1 << 63)


def derive_rng(seed: int, *keys: str | int) -> np.random.Generator:
    """An independent, reproducible stream for ``seed`` and a path of keys.

    ``derive_rng(study_seed, participant_id, block, "complexity")`` returns the
    same stream in every process and Python version (keys are hashed with
    BLAKE2b, not the salted built-in ``hash``); different key paths give
    statistically independent streams (``np.random.SeedSequence`` spawn keys).
    ``seed`` must be a non-negative integer.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    spawn_key = tuple(_key_word(k) for k in keys)
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(entropy=int(seed), spawn_key=spawn_key)))


# --- Shelves -------------------------------------------------------------------

def _check_shelf_args(n_trials: int, shelf_size: int) -> None:
    if n_trials < 0:
        raise ValueError(f"n_trials must be ≥ 0, got {n_trials}")
    if shelf_size < 1:
        raise ValueError(f"shelf_size must be ≥ 1, got {shelf_size}")


def shelves(n_trials: int, shelf_size: int) -> list[int]:
    """The 1-based shelf number of each trial (length ``n_trials``).

    Consecutive runs of ``shelf_size`` trials share a shelf; the last shelf
    holds the remainder and may be shorter.
    """
    _check_shelf_args(n_trials, shelf_size)
    return [i // shelf_size + 1 for i in range(n_trials)]


def n_shelves(n_trials: int, shelf_size: int) -> int:
    """Number of shelves in a block: ceil(n_trials / shelf_size)."""
    _check_shelf_args(n_trials, shelf_size)
    return -(-n_trials // shelf_size)


def is_shelf_end(trial_index: int, n_trials: int, shelf_size: int) -> bool:
    """Whether the trial at 0-based ``trial_index`` is the last of its shelf
    (so the shelf questionnaire follows it). The block's last trial always is."""
    _check_shelf_args(n_trials, shelf_size)
    if not 0 <= trial_index < n_trials:
        raise ValueError(f"trial_index must be in [0, {n_trials}), got {trial_index}")
    return (trial_index + 1) % shelf_size == 0 or trial_index == n_trials - 1


# --- Counterbalancing ------------------------------------------------------------

def _williams_first_row(n: int) -> list[int]:
    """0, 1, n-1, 2, n-2, ...: successive differences are all distinct mod n for even n."""
    row, low, high = [0], 1, n - 1
    while len(row) < n:
        row.append(low)
        low += 1
        if len(row) < n:
            row.append(high)
            high -= 1
    return row


def block_orders(n_blocks: int, method: OrderMethod = "all") -> list[BlockOrder]:
    """Candidate block orders, each a permutation of the 0-based block indices.

    - ``"all"``: all n! permutations in lexicographic order (n ≤ 8).
    - ``"latin"``: the n rows of a cyclic Latin square built from the Williams
      sequence 0, 1, n−1, 2, n−2, …: every block appears once in every row and
      every position. For even n it is a Williams design: each block is
      immediately followed by each other block exactly once. For odd n the
      first-order carryover is *not* balanced (that needs 2n rows, the square
      and its mirror image); use ``"all"`` when it matters.
    """
    if n_blocks < 1:
        raise ValueError(f"n_blocks must be ≥ 1, got {n_blocks}")
    if method == "all":
        if n_blocks > MAX_BLOCKS_ALL_ORDERS:
            raise ValueError(f"{n_blocks}! orders is too many; use method='latin' (n_blocks ≤ {MAX_BLOCKS_ALL_ORDERS} "
                             "for 'all')")
        return list(itertools.permutations(range(n_blocks)))
    if method == "latin":
        first = _williams_first_row(n_blocks)
        return [tuple((b + shift) % n_blocks for b in first) for shift in range(n_blocks)]
    raise ValueError(f"unknown method {method!r}; expected 'all' or 'latin'")


@dataclass(frozen=True)
class Assignment:
    """One counterbalancing decision, with what is needed to audit it."""

    order: tuple
    counts_before: tuple[tuple[tuple, int], ...]  # (order, active count) for every candidate, in candidate order
    tied_orders: tuple[tuple, ...]  # the orders with the fewest active participants
    method: str = ASSIGNMENT_RULE

    def audit_line(self) -> str:
        counts = ", ".join(f"{_fmt(o)}={c}" for o, c in self.counts_before)
        tied = ", ".join(_fmt(o) for o in self.tied_orders)
        return f"assigned {_fmt(self.order)} by {self.method}; active counts {counts}; tied {tied}"


def _fmt(order: tuple) -> str:
    return "-".join(str(b) for b in order)


def _counts_for(orders: Sequence[tuple], active_counts: Mapping[tuple, int]) -> dict[tuple, int]:
    known = set(orders)
    unknown = [k for k in active_counts if tuple(k) not in known]
    if unknown:
        raise ValueError(f"counts given for orders that are not candidates: {unknown}")
    counts = {o: int(active_counts.get(o, 0)) for o in orders}
    negative = [o for o, c in counts.items() if c < 0]
    if negative:
        raise ValueError(f"active counts must be ≥ 0; negative for {negative}")
    return counts


def assign_block_order(orders: Sequence[tuple], active_counts: Mapping[tuple, int],
                       rng: np.random.Generator) -> Assignment:
    """The order for the next participant: one with the fewest active participants.

    An order is a tuple of block labels (indices from ``block_orders`` or block
    names); ``active_counts`` maps an order to the number of participants who started
    with it and did not abandon (in progress or completed); missing orders
    count 0. Ties are broken uniformly at random with ``rng``. Pure: the caller
    stores the result and updates its counts.
    """
    orders = [tuple(o) for o in orders]
    if not orders:
        raise ValueError("at least one candidate order is needed")
    if len(set(orders)) != len(orders):
        raise ValueError("candidate orders must be distinct")
    counts = _counts_for(orders, active_counts)
    fewest = min(counts.values())
    tied = tuple(o for o in orders if counts[o] == fewest)
    chosen = tied[int(rng.integers(len(tied)))]
    return Assignment(order=chosen, counts_before=tuple(counts.items()), tied_orders=tied)
