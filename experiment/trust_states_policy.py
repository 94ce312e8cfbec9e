"""The trust-aware policy of a K-state trust model (issue 40): value iteration on the belief simplex.

The generalisation of ``experiment.belief_mdp`` from the 1-D belief P(T = high) to a belief b over K trust states
(a point of the (K - 1)-simplex). Everything else is as there: actions auto / ask, the next complexity i.i.d.
Bernoulli(p_high), one step branching over the human action o and the experience E':

    P(o, E' | b, C, a) = sum_k b(k) P(o | k, C, a) P(E' | o, C, a),
    b' = (b conditioned on o ("bayes") or b itself ("paper"))  @  transition[C, a, E'],

reward R(b, C, a) = sum_k b(k) sum_o P(o | k, C, a) E[R | C, a, o], and the same stopping rule
||V_{k+1} - V_k||_inf < tol (1 - gamma) / (2 gamma). E_t is left out of the state: neither the reward nor the
transition depends on it (``belief_mdp`` keeps it and reports that the policy does not depend on it).

Grid. All beliefs whose coordinates are multiples of 1/n (``resolution`` n): C(n + K - 1, K - 1) points; at K = 2
these are the n + 1 points of ``belief_mdp``'s grid of n + 1, in the same order (ascending P(state 1)). V at an
off-grid b' is interpolated in Freudenthal's triangulation of that grid (Lovejoy 1991): b' lies in one small
simplex of K grid points and gets their barycentric weights. At K = 2 that is exactly ``belief_mdp``'s linear
interpolation between the two neighbouring points.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations, product

import numpy as np
from scipy import sparse

from experiment import defaults
from experiment.belief_mdp import DEFAULT_TOLERANCE, MAX_ITERATIONS, check_solver_arguments
from experiment.iohmm import BeliefUpdate, ModelError
from experiment.task import (
    Complexity,
    Experience,
    HumanAction,
    RobotAction,
    TaskParams,
    expected_reward_given_action,
    p_positive_experience,
)
from experiment.trust_states import KStateParams

_AUTO, _ASK = RobotAction.AUTO.code, RobotAction.ASK.code
MAX_GRID_POINTS = 2_000_000  # a guard against a resolution that would not fit in memory


@dataclass(frozen=True)
class KPolicySolution:
    """The solved belief MDP of a K-state model. Codes as in ``experiment.task`` (C: low 0 / high 1; A: auto 0 / ask 1).

    - ``counts`` (M, K) int: grid point m is the belief counts[m] / resolution.
    - ``beliefs`` (M, K): those beliefs.
    - ``q`` (2 C, M, 2 A): Q(C_t, b, a); ``values`` (2 C, M) = max_a Q.
    - ``policy`` (2 C, M) int8: action code per grid point; ties go to ask (as in ``belief_mdp``).
    """

    counts: np.ndarray
    beliefs: np.ndarray
    q: np.ndarray
    values: np.ndarray
    policy: np.ndarray
    resolution: int
    iterations: int
    residual: float
    tolerance: float
    p_high: float
    discount: float
    belief_update: BeliefUpdate

    @property
    def n_states(self) -> int:
        return int(self.counts.shape[1])

    def action(self, belief: np.ndarray, complexity: Complexity) -> RobotAction:
        """The optimal action at any belief (K,) (Q interpolated on the grid; ties -> ask)."""
        b = np.asarray(belief, dtype=float).reshape(1, -1)
        if b.shape[1] != self.n_states or (b < 0).any() or not np.isclose(b.sum(), 1.0):
            raise ValueError(f"belief must be a distribution over {self.n_states} states, got {belief}")
        vertices, weights = interpolation(self.counts, self.resolution, b)  # (1, K), (1, K)
        gain = self.q[Complexity(complexity).code, vertices[0]] @ np.array([1.0, -1.0])  # (K,)
        return RobotAction.AUTO if float(weights[0] @ gain) > 0.0 else RobotAction.ASK


def simplex_grid(n_states: int, resolution: int) -> np.ndarray:
    """(M, K) int: every composition of ``resolution`` into K parts, sorted by (x_{K-1}, ..., x_1) ascending."""
    cuts = np.array(list(combinations(range(resolution + n_states - 1), n_states - 1)), dtype=np.int64)
    bounds = np.concatenate([np.full((len(cuts), 1), -1), cuts, np.full((len(cuts), 1), resolution + n_states - 1)],
                            axis=1)
    counts = np.diff(bounds, axis=1) - 1  # stars and bars: the gaps between the bars
    return counts[np.argsort(_codes(counts, resolution), kind="stable")]


def _codes(counts: np.ndarray, resolution: int) -> np.ndarray:
    """(M,) an integer per composition (x_1, ..., x_{K-1} in base n + 1; x_0 is implied); at K = 2 it is x_1."""
    return counts[:, 1:] @ (resolution + 1) ** np.arange(counts.shape[1] - 1, dtype=np.int64)


def interpolation(counts: np.ndarray, resolution: int, beliefs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Freudenthal interpolation: beliefs (B, K) -> grid indices (B, K) and barycentric weights (B, K).

    In cumulative coordinates y_i = n sum_{j >= i} b_j the grid is the integer lattice; the vertices are
    floor(y) plus the unit steps of the coordinates in descending order of their fractional part.
    """
    n = resolution
    b = np.clip(beliefs, 0.0, None)
    b = b / b.sum(axis=1, keepdims=True)
    y = n * np.cumsum(b[:, ::-1], axis=1)[:, ::-1]  # (B, K), y_0 = n
    y[:, 0] = n
    base = np.floor(y)
    frac = y - base
    frac[:, 0] = 0.0
    order = np.argsort(-frac[:, 1:], axis=1, kind="stable") + 1  # (B, K - 1): ties -> lower index first
    sorted_frac = np.take_along_axis(frac, order, axis=1)
    weights = -np.diff(np.concatenate([np.ones((len(b), 1)), sorted_frac, np.zeros((len(b), 1))], axis=1), axis=1)
    steps = np.zeros((b.shape[1], *y.shape), dtype=np.int64)  # (K vertices, B, K)
    for m in range(1, b.shape[1]):
        steps[m] = steps[m - 1]
        np.put_along_axis(steps[m], order[:, m - 1:m], 1, axis=1)
    vertex_y = base.astype(np.int64)[None] + steps  # (K vertices, B, K)
    vertex_x = vertex_y - np.concatenate([vertex_y[..., 1:], np.zeros((*vertex_y.shape[:2], 1), np.int64)], axis=-1)
    invalid = (vertex_x < 0).any(axis=-1) | (vertex_x > n).any(axis=-1)  # only with weight 0 (b on the boundary)
    vertex_x[invalid] = vertex_x[0][np.nonzero(invalid)[1]]
    grid_codes = _codes(counts, n)
    index = np.searchsorted(grid_codes, _codes(vertex_x.reshape(-1, b.shape[1]), n)).reshape(vertex_x.shape[:2])
    return np.ascontiguousarray(index.T), weights


def solve_k_state_policy(params: KStateParams, task: TaskParams = TaskParams(), *, p_high: float,
                         resolution: int = 1000, discount: float = defaults.DISCOUNT,
                         belief_update: BeliefUpdate = "bayes", tol: float = DEFAULT_TOLERANCE) -> KPolicySolution:
    """Value iteration on the belief simplex with grid step 1 / ``resolution`` (see the module docstring).

    Arguments as ``belief_mdp.solve_belief_mdp``; ``resolution`` n gives C(n + K - 1, K - 1) grid points (n = 1000
    at K = 2 is ``grid=1001``). Raises ``ModelError`` when a transition the policy reaches is not estimated (NaN).
    """
    _check_arguments(p_high, resolution, discount, belief_update, tol)
    counts = simplex_grid(params.n_states, resolution)
    if len(counts) > MAX_GRID_POINTS:
        raise ValueError(f"{len(counts)} grid points are too many; lower the resolution")
    beliefs = counts / resolution
    kernel, reward = _model(params, task, counts, resolution, belief_update)  # (2 A * 2 C * M, M), (2 A, 2 C, M)
    q, iterations, residual = _value_iteration(kernel, reward, p_high, discount, tol)  # (2 C, M, 2 A)
    policy = np.where(q[..., _AUTO] - q[..., _ASK] > 0.0, _AUTO, _ASK).astype(np.int8)
    values = q.max(axis=-1)
    for array in (counts, beliefs, q, values, policy):
        array.setflags(write=False)
    return KPolicySolution(counts=counts, beliefs=beliefs, q=q, values=values, policy=policy, resolution=resolution,
                           iterations=iterations, residual=residual, tolerance=tol, p_high=float(p_high),
                           discount=float(discount), belief_update=belief_update)


def ask_share(solution: KPolicySolution) -> dict[Complexity, float]:
    """Per complexity, the share of grid points where the robot asks (the asking region's share of the simplex)."""
    return {c: float((solution.policy[c.code] == _ASK).mean()) for c in Complexity}


def mean_belief_where(solution: KPolicySolution, action: RobotAction) -> dict[Complexity, np.ndarray | None]:
    """Per complexity, the centroid (K,) of the grid points where the robot takes ``action`` (None if nowhere)."""
    chosen = {c: solution.policy[c.code] == action.code for c in Complexity}
    return {c: (solution.beliefs[m].mean(axis=0) if m.any() else None) for c, m in chosen.items()}


def describe(solution: KPolicySolution) -> list[str]:
    """The policy in words, one line per complexity: where on the belief simplex the robot asks."""
    def belief(vector: np.ndarray | None) -> str:
        return "–" if vector is None else "(" + ", ".join(f"{x:.2f}" for x in vector) + ")"

    share, asks, acts = ask_share(solution), mean_belief_where(solution, RobotAction.ASK), mean_belief_where(
        solution, RobotAction.AUTO)
    lines = []
    for c in Complexity:
        if share[c] in (0.0, 1.0):
            lines.append(f"{c.value:>4} complexity: always {'asks' if share[c] == 1.0 else 'acts autonomously'}")
        else:
            lines.append(f"{c.value:>4} complexity: asks on {share[c]:.0%} of the belief simplex; mean belief "
                         f"(state_0 … state_{solution.beliefs.shape[1] - 1}) where it asks {belief(asks[c])}, "
                         f"where it acts alone {belief(acts[c])}")
    return lines


def _check_arguments(p_high: float, resolution: int, discount: float, belief_update: str, tol: float) -> None:
    if resolution < 1:
        raise ValueError(f"the grid resolution must be at least 1, got {resolution}")
    check_solver_arguments(p_high, discount, belief_update, tol)


def _p_observation(params: KStateParams, c: Complexity, a: RobotAction, o: HumanAction) -> np.ndarray:
    """P(o | state, C, a), shape (K,): when the robot asks the human always intervenes (assists)."""
    rely = params.p_rely[c.code] if a == RobotAction.AUTO else np.zeros(params.n_states)
    return np.asarray(rely if o == HumanAction.RELY else 1.0 - rely)


def _branches(params: KStateParams, task: TaskParams, c: Complexity, a: RobotAction, beliefs: np.ndarray,
              method: BeliefUpdate):
    """Yield (probability (M,), next belief (M, K)) per (o, E') branch that can happen."""
    for o in HumanAction:
        joint = beliefs * _p_observation(params, c, a, o)  # (M, K)
        p_o = joint.sum(axis=1)
        weights = beliefs
        if method == "bayes":
            weights = np.divide(joint, p_o[:, None], out=beliefs.copy(), where=p_o[:, None] > 0.0)
        p_positive = p_positive_experience(c, a, o, task)
        for e, p_e in ((Experience.NEGATIVE, 1.0 - p_positive), (Experience.POSITIVE, p_positive)):
            probability = p_o * p_e
            live = probability > 0.0
            if not live.any():
                continue  # this branch cannot happen: its (possibly NaN) parameters are never read
            matrix = params.transition[c.code, a.code, e.code]  # (K, K)
            missing = np.isnan(matrix).any(axis=1)
            if (weights[live][:, missing] > 0.0).any():
                raise ModelError(f"the model has no transition estimate for {e} experience after {a} in {c} "
                                 "complexity, which the belief MDP reaches with positive probability")
            yield probability, weights @ np.nan_to_num(matrix)


def _model(params: KStateParams, task: TaskParams, counts: np.ndarray, resolution: int,
           method: BeliefUpdate) -> tuple[sparse.csr_matrix, np.ndarray]:
    """Transition matrix (rows (a, C, b): 2 A * 2 C * M; columns b': M) and rewards (2 A, 2 C, M)."""
    m = len(counts)
    beliefs = counts / resolution
    reward = np.empty((2, 2, m))
    rows, cols, values = [], [], []
    for c, a in product(Complexity, RobotAction):
        r = sum(_p_observation(params, c, a, o) * expected_reward_given_action(c, a, o, task) for o in HumanAction)
        reward[a.code, c.code] = beliefs @ np.asarray(r)
        row = (a.code * 2 + c.code) * m + np.arange(m)
        for probability, nxt in _branches(params, task, c, a, beliefs, method):
            index, weights = interpolation(counts, resolution, nxt)  # (M, K) each
            rows.append(np.repeat(row, params.n_states))
            cols.append(index.ravel())
            values.append((probability[:, None] * weights).ravel())
    kernel = sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                               shape=(4 * m, m))
    kernel.sum_duplicates()
    return kernel, reward


def _value_iteration(kernel: sparse.csr_matrix, reward: np.ndarray, p_high: float, discount: float,
                     tol: float) -> tuple[np.ndarray, int, float]:
    """Q (2 C, M, 2 A); iterations; last ||V_{k+1} - V_k||_inf (the stopping rule of ``belief_mdp``)."""
    m = reward.shape[2]
    scaled = (discount * kernel).tocsr()
    r = reward.ravel()  # (2 A, 2 C, M)
    p_c = np.array([1.0 - p_high, p_high])
    bound = np.inf if discount == 0.0 else tol * (1.0 - discount) / (2.0 * discount)
    v = np.zeros((2, m))  # (C, M)
    residual = np.inf
    for iteration in range(1, MAX_ITERATIONS + 1):
        q = (r + scaled @ (p_c @ v)).reshape(2, 2, m)  # (2 A, 2 C, M)
        v_next = np.maximum(q[0], q[1])
        residual = float(np.abs(v_next - v).max())
        v = v_next
        if residual < bound:
            return np.ascontiguousarray(np.moveaxis(q, 0, -1)), iteration, residual
    raise RuntimeError(f"value iteration did not converge in {MAX_ITERATIONS} sweeps (residual {residual:.3g})")
