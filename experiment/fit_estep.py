"""The E-step of the trust IOHMM: scaled forward–backward, likelihood and its exact gradient.

Shapes: R restarts (parameter vectors fitted side by side), N sequences,
T trials (sequences padded to the longest), P = 21 parameters in the order of
``iohmm.PARAMETER_NAMES``. The E-step is a scaled forward–backward pass for
K = 2 states over (T, N, R) arrays; the time loops do elementwise operations
on (N, R) rows only. Padding and the step after a sequence's last trial use
probability-1 emissions and "stay" transitions, so they change nothing.

Each parameter θ is a Bernoulli probability. The E-step returns, per restart,
the sensitivities G1 = ∂L/∂P("1") and G0 = ∂L/∂P("0") summed over the trials
that use θ's slot. From them: expected counts n1 = θ·G1, n0 = (1−θ)·G0 (the
EM statistics) and the exact gradient dL/dθ = G1 − G0 (Fisher's identity,
n1/θ − n0/(1−θ), without dividing by θ, so exact 0 and 1 are fine).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from experiment.iohmm import (
    EMISSIONS_OF,
    INITIAL,
    N_PARAMETERS,
    N_TRANSITION_INPUTS,
    PARAMETER_NAMES,
    TRANSITIONS_FROM,
    IOHMMParams,
    ModelError,
)
from experiment.sequences import Sequence

_NO_TRANSITION = N_TRANSITION_INPUTS  # trans code of "no transition" (stay): after the last trial, padding
_N_EMIT_CODES = 4  # emit codes c·2 + o of an autonomous trial
_NO_EMISSION = _N_EMIT_CODES  # emit code of a probability-1 emission: the robot asked, padding
_TABLE_OFFSETS = np.cumsum([0, _NO_TRANSITION + 1, _NO_TRANSITION + 1, _NO_EMISSION + 1])  # _gather's blocks
_BIG = 1e280  # cap of the backward sensitivities of a state the filter rules out
_MAX_CELLS = 1_000_000  # trials × sequences × restarts per E-step batch (scratch: 13 × 8 bytes per cell)
_BUFFERS = {"gather": 4, "pred": 1, "filt": 1, "c": 1, "dd": 2, "b": 2, "u": 2}  # scratch, in units of T·N·R


class Data:
    """Sequences as per-cell input codes, plus E-step scratch arrays.

    Cell (trial t, sequence n) is flattened to t·N + n. ``trans`` holds the
    input combo k = (c·2 + a)·2 + e of the transition after trial t (8: none,
    after the last trial and in padding); ``emit`` holds c·2 + o of an
    autonomous trial (4: probability-1 emission, when the robot asked and in padding).
    ``gather`` indexes ``_gather``'s table, whose blocks (at ``_TABLE_OFFSETS``)
    give p_lh and p_hh by trans code, then e_l and e_h by emit code.
    """

    def __init__(self, sequences: list[Sequence]) -> None:
        seqs = [s for s in sequences if len(s)]
        if not seqs:
            raise ValueError("no trials to fit")
        self.n_sequences, self.n_trials = len(seqs), sum(len(s) for s in seqs)
        T, N = max(len(s) for s in seqs), len(seqs)
        trans, emit = np.full((T, N), _NO_TRANSITION, dtype=np.intp), np.full((T, N), _NO_EMISSION, dtype=np.intp)
        for n, s in enumerate(seqs):
            c, a, o, e = (x.astype(np.intp) for x in (s.complexity, s.robot_action, s.human_action, s.experience))
            trans[:len(s) - 1, n] = ((c * 2 + a) * 2 + e)[:-1]
            emit[:len(s), n] = np.where(a == 0, c * 2 + o, _NO_EMISSION)
        self.shape, self.trans, self.emit = (T, N), trans.ravel(), emit.ravel()  # (T·N,) each
        self.gather = np.concatenate([codes + offset for codes, offset in
                                      zip((self.trans, self.trans, self.emit, self.emit), _TABLE_OFFSETS, strict=True)])
        used = np.zeros(N_PARAMETERS, dtype=bool)
        used[INITIAL] = True
        inputs = np.bincount(self.trans, minlength=_NO_TRANSITION + 1)[:_NO_TRANSITION] > 0  # by input k
        complexities = np.bincount(self.emit, minlength=_NO_EMISSION + 1)[:_N_EMIT_CODES].reshape(2, 2).any(axis=1)
        for state in (0, 1):
            used[TRANSITIONS_FROM[state]], used[EMISSIONS_OF[state]] = inputs, complexities
        self.exercised = used  # (P,) the data use this slot
        self._scratch: dict[str, np.ndarray] = {}
        self._views: tuple[Any, ...] = ()

    def workspace(self, R: int) -> tuple[dict[str, np.ndarray], dict[str, list[np.ndarray]]]:
        """Scratch arrays and their per-trial rows, kept between E-steps (no page faults, no view churn).

        "gather" (4, T, N, R): p_lh = P(high | low), p_hh = P(high | high) of
        the transition after t, e_l, e_h = P(o_t | low / high). "dd" (T, 2, N, R):
        d = p_hh − p_lh, de = e_h − e_l, later r = e / c. b, u (T, 2, N, R):
        stacked over the state (low, high). pred, filt, c: (T, N, R). Rows are
        C-contiguous (N, R) or (2, N, R). "bins_*": bincount index code·R + restart.
        """
        if self._views and self._views[0] == R:
            return self._views[1], self._views[2]
        T, N = self.shape
        size = T * N * R
        if not self._scratch or self._scratch["c"].size < size:
            self._scratch = {name: np.empty(units * size) for name, units in _BUFFERS.items()}
        shape = {1: (T, N, R), 2: (T, 2, N, R), 4: (4, T, N, R)}
        a = {name: self._scratch[name][:units * size].reshape(shape[units]) for name, units in _BUFFERS.items()}
        a.update(zip(("p_lh", "p_hh", "e_l", "e_h"), a["gather"], strict=True))
        a.update(d=a["dd"][:, 0], de=a["dd"][:, 1], r=a["dd"],
                 bins_trans=(self.trans[:(T - 1) * N, None] * R + np.arange(R)).ravel(),
                 bins_emit=(self.emit[:, None] * R + np.arange(R)).ravel())
        names = ("p_lh", "p_hh", "e_l", "e_h", "pred", "filt", "c", "d", "de", "r", "b", "u")
        rows = {name: list(a[name]) for name in names}
        rows.update({f"{name}_{j}": list(a[name][:, i]) for name in ("b", "u") for i, j in enumerate("lh")})
        self._views = (R, a, rows)
        return a, rows


class EStep(NamedTuple):
    loglik: np.ndarray  # (R,)
    n1: np.ndarray  # (R, P) expected count of "1" (to high / rely / starts high)
    n0: np.ndarray  # (R, P) expected count of "0"
    grad: np.ndarray  # (R, P) dL/dθ


def _gather(data: Data, theta: np.ndarray, ws: dict[str, np.ndarray]) -> None:
    """Fill p_lh, p_hh, e_l, e_h (T, N, R) from theta (R, P) with one table look-up.

    ``np.take`` with mode="clip" skips bounds checks and, unlike a one-hot
    matrix product, uses no BLAS threads (which stall when the other core is busy).
    """
    R = theta.shape[0]
    rely = [theta[:, EMISSIONS_OF[s]].T for s in (0, 1)]  # rows: complexity
    emission = [np.stack([r[0], 1 - r[0], r[1], 1 - r[1], np.ones(R)]) for r in rely]  # rows: emit code
    table = np.concatenate([theta[:, TRANSITIONS_FROM[0]].T, np.zeros((1, R)),
                            theta[:, TRANSITIONS_FROM[1]].T, np.ones((1, R))] + emission)
    np.take(table, data.gather, axis=0, out=ws["gather"].reshape(-1, R), mode="clip")


def _forward(theta0: np.ndarray, rows: dict[str, list[np.ndarray]]) -> None:
    """Scaled forward pass; theta0 (R,) = P(T_1 = high).

    Fills pred = P(high | o_<t), filt = P(high | o_≤t) and c = P(o_t | o_<t).
    A zero c (data the model rules out) makes that restart NaN, nothing else.
    """
    p_lh, d, e_l, e_h, de, pred, filt, c = (rows[k] for k in ("p_lh", "d", "e_l", "e_h", "de", "pred", "filt", "c"))
    pred[0][...] = theta0
    for t in range(len(pred)):
        if t:
            np.multiply(filt[t - 1], d[t - 1], out=pred[t])
            np.add(pred[t], p_lh[t - 1], out=pred[t])
        np.multiply(pred[t], de[t], out=c[t])
        np.add(c[t], e_l[t], out=c[t])
        np.multiply(pred[t], e_h[t], out=filt[t])
        np.divide(filt[t], c[t], out=filt[t])


def _backward(rows: dict[str, list[np.ndarray]], clip: bool) -> None:
    """Scaled backward pass given r = e / c: fills β̂ (b) and u = r·β̂ = ∂L/∂e(t).

    β̂ of a state the filter rules out can overflow; ``clip`` caps u at 1e280.
    """
    p_lh, p_hh, r, b, u = (rows[k] for k in ("p_lh", "p_hh", "r", "b", "u"))
    b_l, b_h, u_l, u_h = (rows[k] for k in ("b_l", "b_h", "u_l", "u_h"))
    b[-1][...] = 1.0
    diff = np.empty(u_l[0].shape)
    for t in range(len(b) - 1, -1, -1):
        np.multiply(r[t], b[t], out=u[t])
        if clip:
            np.minimum(u[t], _BIG, out=u[t])
        if t:
            np.subtract(u_h[t], u_l[t], out=diff)
            np.multiply(p_lh[t - 1], diff, out=b_l[t - 1])
            np.add(b_l[t - 1], u_l[t], out=b_l[t - 1])
            np.multiply(p_hh[t - 1], diff, out=b_h[t - 1])
            np.add(b_h[t - 1], u_l[t], out=b_h[t - 1])


def _sensitivities(ws: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """G1, G0 (R, P) from the passes (c must hold 1/c; e_l, e_h are used as scratch).

    Transition from state i to j after trial t: filt_i(t)·u_j(t+1); emission
    of state j at t: pred_j(t)·β̂_j(t)/c_t; initial state j: u_j(0).
    """
    filt, u, b, w, pred = ws["filt"], ws["u"], ws["b"], ws["c"], ws["pred"]
    R = filt.shape[-1]

    def sums(x: np.ndarray, bins: str, n: int) -> np.ndarray:  # (n, R): x summed per input code
        return np.bincount(ws[bins], weights=x.ravel(), minlength=(n + 1) * R)[:n * R].reshape(n, R)

    G1, G0 = np.zeros((R, N_PARAMETERS)), np.zeros((R, N_PARAMETERS))
    G1[:, INITIAL], G0[:, INITIAL] = u[0, 1].sum(axis=0), u[0, 0].sum(axis=0)
    prod = ws["e_l"][:-1]
    for j, G in ((1, G1), (0, G0)):
        np.multiply(filt[:-1], u[1:, j], out=prod)  # from high
        G[:, TRANSITIONS_FROM[1]] = sums(prod, "bins_trans", N_TRANSITION_INPUTS).T
        np.subtract(u[1:, j], prod, out=prod)  # from low: (1 − filt)·u
        G[:, TRANSITIONS_FROM[0]] = sums(prod, "bins_trans", N_TRANSITION_INPUTS).T
    v_h = np.multiply(pred, w, out=ws["e_l"])
    v_l = np.subtract(w, v_h, out=ws["e_h"])
    for j, v in ((0, v_l), (1, v_h)):
        v *= b[:, j]  # ∂L/∂e_j(t)
        s = sums(v, "bins_emit", _N_EMIT_CODES)  # rows (c, o): rely counts for θ, intervene for 1 − θ
        G1[:, EMISSIONS_OF[j]], G0[:, EMISSIONS_OF[j]] = s[0::2].T, s[1::2].T
    return G1, G0


def e_step(data: Data, theta: np.ndarray) -> EStep:
    """Forward–backward for parameter vectors theta (R, P) in [0, 1]; NaN-free, −inf loglik if impossible."""
    T, N = data.shape
    chunk = max(1, _MAX_CELLS // (T * N))
    if theta.shape[0] > chunk:  # bound the scratch memory
        parts = [e_step(data, theta[i:i + chunk]) for i in range(0, theta.shape[0], chunk)]
        return EStep(*(np.concatenate(x) for x in zip(*parts, strict=True)))
    ws, rows = data.workspace(theta.shape[0])
    _gather(data, theta, ws)
    with np.errstate(all="ignore"):
        np.subtract(ws["p_hh"], ws["p_lh"], out=ws["d"])
        np.subtract(ws["e_h"], ws["e_l"], out=ws["de"])
        _forward(theta[:, INITIAL], rows)
        c = ws["c"]
        np.divide(ws["e_l"], c, out=ws["r"][:, 0])
        np.divide(ws["e_h"], c, out=ws["r"][:, 1])
        loglik = np.log(c, out=ws["e_l"]).sum(axis=(0, 1))
        loglik[np.isnan(loglik)] = -np.inf
        ok = np.isfinite(loglik)
        np.divide(1.0, c, out=c)
        _backward(rows, clip=False)
        if not np.isfinite(ws["u"][0][..., ok]).all():
            _backward(rows, clip=True)
        G1, G0 = _sensitivities(ws)
    G1[~ok] = G0[~ok] = 0.0
    G1, G0 = (np.maximum(np.nan_to_num(G, nan=0.0, posinf=_BIG), 0.0) for G in (G1, G0))  # sums of terms ≥ 0
    return EStep(loglik, theta * G1, (1.0 - theta) * G0, G1 - G0)


def _vector(params: IOHMMParams, data: Data) -> np.ndarray:
    """(1, P) parameter vector; NaN allowed only in slots the data never use."""
    theta = params.to_vector()
    missing = [n for n, v, u in zip(PARAMETER_NAMES, theta, data.exercised, strict=True) if u and np.isnan(v)]
    if missing:
        raise ModelError(f"the model has no estimate for parameters the data use: {', '.join(missing)}")
    return np.where(np.isnan(theta), 0.5, theta)[None]


def log_likelihood(params: IOHMMParams, sequences: list[Sequence]) -> float:
    """Total log-likelihood of the sequences (−inf if the model rules an observation out)."""
    data = Data(sequences)
    return float(e_step(data, _vector(params, data)).loglik[0])


def log_likelihood_gradient(params: IOHMMParams, sequences: list[Sequence]) -> np.ndarray:
    """(P,) exact dL/dθ (Fisher's identity); NaN for parameters the data never use."""
    data = Data(sequences)
    return np.where(data.exercised, e_step(data, _vector(params, data)).grad[0], np.nan)
