"""Hidden Markov chain pieces shared by the EM and the diagnosis (pure numpy; tested against
exact enumeration): transition matrices, forward-backward, backward sampling, Gibbs updates."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np


def transition_matrix(n_modes: int, stay: float, p_enter: float | None = None,
                      p_leave: float | None = None) -> np.ndarray:
    """(S, S) transition matrix over states ``k + K*d``; S = K, or 2K with a disturbance chain."""
    K = n_modes
    Pk = np.full((K, K), (1.0 - stay) / (K - 1)) if K > 1 else np.ones((1, 1))
    if K > 1:
        np.fill_diagonal(Pk, stay)
    if p_enter is None:
        return Pk
    Pd = np.array([[1.0 - p_enter, p_enter], [p_leave, 1.0 - p_leave]])
    return np.kron(Pd, Pk)  # index k + K*d: outer factor d, inner factor k


def _log_normalise(logp: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    m = logp.max(axis=axis, keepdims=True)
    p = np.exp(logp - m)
    z = p.sum(axis=axis, keepdims=True)
    return p / z, (np.log(z) + m).squeeze(axis)


def forward_backward(loglik: np.ndarray, A: np.ndarray, init: np.ndarray,
                     starts: Sequence[int] = (0,)) -> tuple[np.ndarray, np.ndarray, float]:
    """Scaled forward-backward. loglik (T, S), A (S, S), init (S,); the chain restarts at each
    index in ``starts`` (separate logs). Returns filtered alpha (T, S), marginals (T, S) and the
    log marginal likelihood of the sequence."""
    T, S = loglik.shape
    is_start = np.zeros(T, bool)
    is_start[list(starts)] = True
    lik, shift = _log_normalise(loglik)           # per-row scaled likelihoods
    alpha = np.empty((T, S))
    logZ = float(shift.sum())
    for t in range(T):
        pred = init if is_start[t] else alpha[t - 1] @ A
        a = pred * lik[t]
        c = a.sum()
        alpha[t] = a / c
        logZ += math.log(c)
    beta = np.ones((T, S))
    for t in range(T - 2, -1, -1):
        if is_start[t + 1]:
            beta[t] = 1.0
            continue
        b = A @ (lik[t + 1] * beta[t + 1])
        beta[t] = b / b.sum()
    post = alpha * beta
    post /= post.sum(1, keepdims=True)
    return alpha, post, logZ


def ffbs_sample(alpha: np.ndarray, A: np.ndarray, rng: np.random.Generator,
                starts: Sequence[int] = (0,)) -> np.ndarray:
    """Backward sampling of a whole state sequence from filtered ``alpha`` (T, S)."""
    T, S = alpha.shape
    is_start = np.zeros(T + 1, bool)
    is_start[list(starts)] = True
    is_start[T] = True
    s = np.empty(T, int)
    u = rng.random(T)
    for t in range(T - 1, -1, -1):
        p = alpha[t] if is_start[t + 1] else alpha[t] * A[:, s[t + 1]]
        c = np.cumsum(p)
        s[t] = min(int(np.searchsorted(c, u[t] * c[-1], side="right")), S - 1)
    return s


def gibbs_conditionals(loglik: np.ndarray, A: np.ndarray, init: np.ndarray, states: np.ndarray,
                       sites: np.ndarray, starts: Sequence[int] = (0,)) -> np.ndarray:
    """p(s_t | s_-t) for each t in ``sites`` given the others' current ``states``: (len(sites), S)."""
    T = loglik.shape[0]
    is_start = np.zeros(T + 1, bool)
    is_start[list(starts)] = True
    is_start[T] = True
    logA = np.log(np.clip(A, 1e-300, None))
    logp = loglik[sites].copy()
    first = is_start[sites]
    logp[first] += np.log(np.clip(init, 1e-300, None))
    prev = np.where(first, 0, states[np.maximum(sites - 1, 0)])
    logp[~first] += logA[prev[~first]]
    has_next = ~is_start[sites + 1]
    nxt = states[np.minimum(sites + 1, T - 1)]
    logp[has_next] += logA[:, nxt[has_next]].T
    p, _ = _log_normalise(logp)
    return p


def gibbs_sweep(loglik: np.ndarray, A: np.ndarray, init: np.ndarray, states: np.ndarray,
                rng: np.random.Generator, starts: Sequence[int] = (0,)) -> tuple[np.ndarray, np.ndarray]:
    """One single-site Gibbs sweep as two exact blocks (even sites, then odd). Returns new states
    and the conditional probabilities used (T, S), a Rao-Blackwellised marginal estimate."""
    T, S = loglik.shape
    states = states.copy()
    probs = np.empty((T, S))
    for parity in (0, 1):
        sites = np.arange(parity, T, 2)
        p = gibbs_conditionals(loglik, A, init, states, sites, starts)
        c = np.cumsum(p, 1)
        states[sites] = np.minimum((c < rng.random(len(sites))[:, None]).sum(1), S - 1)
        probs[sites] = p
    return states, probs


def sequence_log_prior(states: np.ndarray, A: np.ndarray, init: np.ndarray, starts: Sequence[int] = (0,)) -> float:
    T = len(states)
    is_start = np.zeros(T, bool)
    is_start[list(starts)] = True
    lp = float(np.log(init[states[is_start]]).sum())
    idx = np.flatnonzero(~is_start)
    return lp + float(np.log(A[states[idx - 1], states[idx]]).sum())


def _transition_counts(states: np.ndarray, K: int, starts: Sequence[int]) -> dict:
    T = len(states)
    is_start = np.zeros(T, bool)
    is_start[list(starts)] = True
    idx = np.flatnonzero(~is_start)
    a, b = states[idx - 1], states[idx]
    ka, kb, da, db = a % K, b % K, a >= K, b >= K
    return {"pairs": len(idx), "stay": int((ka == kb).sum()),
            "undisturbed": int((~da).sum()), "enter": int((~da & db).sum()),
            "disturbed": int(da.sum()), "leave": int((da & ~db).sum())}
