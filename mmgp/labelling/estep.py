"""The E-step of the EM: new labels from the chain's posterior given the per-sample
likelihoods (its most probable state per sample, or a draw), the posterior marginals and the log
marginal / joint likelihoods."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .hmm import ffbs_sample, forward_backward, gibbs_sweep, sequence_log_prior, transition_matrix


@dataclass
class EStepResult:
    states: np.ndarray        # (T,) new state indices k + K * d
    probs: np.ndarray         # (T, S) posterior marginals
    log_marginal: float       # log p(Y) under the chain
    log_joint: float          # log p(Y, s) at the new states


def chain_matrix(n_modes: int, disturbance: bool, stay: float, p_enter: float, p_leave: float) -> np.ndarray:
    """(S, S) transition matrix of the mode chain, times the disturbance chain when it is on."""
    return transition_matrix(n_modes, stay, p_enter if disturbance else None, p_leave if disturbance else None)


def e_step(loglik: np.ndarray, A: np.ndarray, init_p: np.ndarray, states: np.ndarray, method: str,
           rng: np.random.Generator, starts: Sequence[int]) -> EStepResult:
    """Labels for one sweep. loglik (T, S) per-sample log-likelihoods, A (S, S), init_p (S,),
    ``states`` (T,) the current labels (Gibbs conditions on them), ``method`` "mpm" (each
    sample's most probable state under the posterior marginals: no draw, ``rng`` unused),
    "ffbs" (joint forward-filtering backward-sampling) or "gibbs" (single-site, two interleaved
    blocks)."""
    alpha, post, log_marg = forward_backward(loglik, A, init_p, starts)
    if method == "mpm":
        new_states = post.argmax(1)
        probs = post
    elif method == "ffbs":
        new_states = ffbs_sample(alpha, A, rng, starts)
        probs = post
    else:
        new_states, probs = gibbs_sweep(loglik, A, init_p, states, rng, starts)
    T = len(new_states)
    log_joint = float(loglik[np.arange(T), new_states].sum() + sequence_log_prior(new_states, A, init_p, starts))
    return EStepResult(new_states, probs, float(log_marg), log_joint)


def disturbed_given_modes(loglik: np.ndarray, modes: np.ndarray, n_modes: int, p_enter: float,
                          p_leave: float, starts: Sequence[int] = (0,)) -> np.ndarray:
    """(T,) posterior probability that each sample is disturbed when the mode path is fixed to
    ``modes`` (T,) ints < K. ``loglik`` (T, 2K) per-sample log-likelihoods over states
    ``k + K*d``; ``p_enter``, ``p_leave`` the disturbance chain's switching probabilities.

    The chain's transition matrix factors as (disturbance) x (mode), so along a fixed mode path
    the mode factor is a constant and drops out: what is left is the disturbance chain over each
    sample's own mode's undisturbed / disturbed likelihoods, uniform at each log's start."""
    idx = np.arange(len(modes))
    pair = np.stack([loglik[idx, modes], loglik[idx, n_modes + modes]], axis=1)
    return forward_backward(pair, chain_matrix(1, True, 1.0, p_enter, p_leave), np.full(2, 0.5), starts)[1][:, 1]


def stretches(labels: np.ndarray, starts: Sequence[int] = (0,)) -> tuple[np.ndarray, np.ndarray]:
    """First index and length of every unbroken stretch of one value in ``labels`` (T,), T >= 1;
    a stretch also ends where a new log starts (``starts``)."""
    labels = np.asarray(labels)
    T = len(labels)
    cut = np.ones(T, bool)
    cut[1:] = labels[1:] != labels[:-1]
    cut[[s for s in starts if 0 < s < T]] = True
    first = np.flatnonzero(cut)
    return first, np.diff(np.r_[first, T])


def true_stretches(mask: np.ndarray, starts: Sequence[int] = (0,)) -> list[tuple[int, int]]:
    """Half-open index ranges [a, b) of the unbroken stretches of True in ``mask`` (T,); a
    stretch also ends where a new log starts (``starts``)."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return []
    first, length = stretches(mask, starts)
    keep = mask[first]
    return [(int(a), int(a + n)) for a, n in zip(first[keep], length[keep])]


def runs_shorter_than(flags: np.ndarray, min_len: float, starts: Sequence[int] = (0,)) -> np.ndarray:
    """(T,) bool: the samples of every unbroken stretch of True in ``flags`` (T,) that is shorter
    than ``min_len`` samples; a stretch ends where a new log starts (``starts``)."""
    flags = np.asarray(flags, bool)
    if min_len <= 1 or not flags.any():
        return np.zeros(len(flags), bool)
    first, length = stretches(flags, starts)
    return np.repeat(flags[first] & (length < min_len), length)


def longest_runs_s(labels: np.ndarray, t: np.ndarray | None, n_modes: int, starts: Sequence[int] = (0,)) -> np.ndarray:
    """(n_modes,) the longest unbroken stretch of each mode label in ``labels`` (T,), in seconds
    of ``t`` (T,) (in samples without times); a stretch ends at a label change or where a new log
    starts (``starts``). 0 for a mode no sample carries."""
    labels = np.asarray(labels)
    first, length = stretches(labels, starts)
    if t is None:
        dur = length.astype(float)
    else:
        t = np.asarray(t, dtype=np.float64)
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        dur = t[first + length - 1] - t[first] + dt
    out = np.zeros(n_modes)
    np.maximum.at(out, labels[first], dur)
    return out


def merge_short_runs(labels: np.ndarray, min_len: float, starts: Sequence[int] = (0,)) -> np.ndarray:
    """``labels`` (T,) with every stretch of one label shorter than ``min_len`` samples relabelled
    as a neighbouring stretch, shortest first, taking the longer neighbour's label (the earlier
    one on a tie), until every stretch of each log (``starts``) lasts ``min_len`` or the log is
    one stretch. Stretches of ``min_len`` or more keep their label."""
    out = np.array(labels, copy=True)
    T = len(out)
    bounds = sorted({0, T} | {int(s) for s in starts if 0 < s < T})
    for a, b in zip(bounds[:-1], bounds[1:]):
        seg = out[a:b]                      # a view: relabelled in place
        while True:
            first, length = stretches(seg)
            if len(length) == 1 or length.min() >= min_len:
                break
            i = int(np.argmin(length))
            left = length[i - 1] if i > 0 else -1
            right = length[i + 1] if i + 1 < len(length) else -1
            seg[first[i]:first[i] + length[i]] = seg[first[i - 1] if left >= right else first[i + 1]]
    return out
