"""Prototype inference pieces of mmgp.models.chains against brute force."""
from __future__ import annotations

import itertools

import numpy as np

from mmgp.models.chains import _matched, smoothed_marginals
from mmgp.models.hmm import forward_backward, transition_matrix


def _enumerated_marginals(loglik, A, init, starts):
    T, S = loglik.shape
    post = np.zeros((T, S))
    for seq in itertools.product(range(S), repeat=T):
        lp = 0.0
        for t, s in enumerate(seq):
            lp += np.log(init[s]) if t in starts else np.log(A[seq[t - 1], s])
            lp += loglik[t, s]
        post[np.arange(T), seq] += np.exp(lp)
    return post / post.sum(1, keepdims=True)


def test_smoothed_marginals_from_filtered_alphas_match_enumeration():
    rng = np.random.default_rng(3)
    A = transition_matrix(2, 0.8, 0.2, 0.4)
    init = np.full(4, 0.25)
    loglik = rng.normal(scale=2.0, size=(6, 4))
    starts = [0, 4]
    alpha, _, _ = forward_backward(loglik, A, init, starts)
    assert np.allclose(smoothed_marginals(alpha, A, starts), _enumerated_marginals(loglik, A, init, starts), atol=1e-12)


def test_matched_permutes_mode_columns_to_the_reference():
    rng = np.random.default_rng(0)
    ref = rng.dirichlet(np.ones(3), size=50)
    perm = [2, 0, 1]
    assert np.array_equal(_matched(ref, ref[:, perm]), ref)
