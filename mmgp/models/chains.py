"""Prototypes for seed-independent labels (issue 10), built around MultimodalSEM without changing it.

- :class:`RobustStartSEM`: the chain starts from an iteratively trimmed GP (hyperparameters and
  first labels from the samples the windowed GP explains best) instead of one GP on everything.
- :class:`ChainSet`: several chains, combined by selection on a criterion or by posterior
  averaging; reports how much the chains agreed.
"""
from __future__ import annotations

import math
import time

import numpy as np

from .sem import MultimodalSEM


def _z_max(Y, mean, var) -> np.ndarray:
    """Largest absolute z-score over joints, (T,)."""
    return (np.abs(Y - mean) / np.sqrt(var)).max(1)


class RobustStartSEM(MultimodalSEM):
    """MultimodalSEM whose start is an iteratively trimmed fit.

    ``trim``: fractions of the samples kept in successive refits (smallest out-of-window z-score
    first); the last fit gives the first hyperparameters, and samples whose z-score, rescaled so
    the kept samples have unit mean square, exceeds ``start_cut`` start disturbed."""

    def __init__(self, n_modes: int = 1, *, trim=(0.8, 0.6), start_cut: float = 3.0, **kw):
        super().__init__(n_modes, **kw)
        self.trim = trim
        self.start_cut = start_cut

    def _initial_states(self, X, Y, rng) -> np.ndarray:
        states = super()._initial_states(X, Y, rng) if self.n_modes > 1 else np.zeros(len(Y), int)
        T = len(Y)
        mean, var, gp, _, _ = self._mode_likelihoods(X, Y, np.arange(T), None, True, rng)
        keep = np.arange(T)
        for frac in self.trim:
            z = _z_max(Y, mean, var)
            keep = np.sort(np.argsort(z, kind="stable")[: int(math.ceil(frac * T))])
            mean, var, gp, _, _ = self._mode_likelihoods(X, Y, keep, gp.hyper_, True, rng)
        self._init_hyper = gp.hyper_
        if self.disturbance:
            z = _z_max(Y, mean, var)
            scale = math.sqrt(max(float(np.mean(z[keep] ** 2)), 1e-12))
            dist = z / scale > self.start_cut
            states = (states % self.n_modes) + self.n_modes * dist
        return states


class ChainSet:
    """Several SEM chains on the same data, combined.

    ``n_chains`` chains of ``chain_class`` with seeds ``seed * 1000 + i``; ``combine``:
    "select" keeps the chain with the best ``criterion``, "average" averages the posteriors of
    all chains (mode columns matched to the first chain by overlap). ``criterion``:
    "log_marginal" (mean log p(Y) of the averaging sweeps). Learned: the chosen/averaged
    ``p_disturbed_``, ``disturbed_``, ``labels_``, ``p_mode_``, ``chains_``, ``scores_``,
    ``agreement_`` (smallest pairwise fraction of samples with the same disturbed label)."""

    def __init__(self, n_modes: int = 1, *, n_chains: int = 4, combine: str = "select",
                 criterion: str = "log_marginal", chain_class=MultimodalSEM, seed: int = 0, **kw):
        self.n_modes = n_modes
        self.n_chains = n_chains
        self.combine = combine
        self.criterion = criterion
        self.chain_class = chain_class
        self.seed = seed
        self.kw = kw

    def _score(self, sem) -> float:
        tail = sem.trace_[-max(1, sem.average_last):]
        return float(np.mean([r.log_marginal for r in tail]))

    def fit(self, X, Y, **fit_kw) -> "ChainSet":
        t0 = time.perf_counter()
        self.chains_ = [self.chain_class(n_modes=self.n_modes, seed=self.seed * 1000 + i, **self.kw).fit(X, Y, **fit_kw)
                        for i in range(self.n_chains)]
        self.scores_ = [self._score(c) for c in self.chains_]
        d = np.array([c.disturbed_ for c in self.chains_])
        self.agreement_ = float(min((d[i] == d[j]).mean() for i in range(len(d)) for j in range(i + 1, len(d)))) \
            if len(d) > 1 else 1.0
        if self.combine == "select":
            best = self.chains_[int(np.argmax(self.scores_))]
            self.p_disturbed_, self.p_mode_ = best.p_disturbed_, best.p_mode_
        else:
            self.p_disturbed_ = np.mean([c.p_disturbed_ for c in self.chains_], axis=0)
            self.p_mode_ = np.mean([_matched(self.chains_[0].p_mode_, c.p_mode_) for c in self.chains_], axis=0)
        self.disturbed_ = self.p_disturbed_ > 0.5
        self.labels_ = self.p_mode_.argmax(1)
        self.converged_ = all(c.converged_ for c in self.chains_)
        self.n_sweeps_ = int(sum(c.n_sweeps_ for c in self.chains_))
        self.log_marginal_ = max(self.scores_)
        self.seconds_ = time.perf_counter() - t0
        return self


def _matched(ref: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Columns of ``p`` (T, K) permuted to overlap ``ref`` (T, K) best (brute force over K!)."""
    from itertools import permutations

    K = ref.shape[1]
    best = max(permutations(range(K)), key=lambda perm: float((ref * p[:, list(perm)]).sum()))
    return p[:, list(best)]


# ----------------------------------------------------------------------------------------------
# Benchmark hooks (benchmarks/bench_labels.py)
# ----------------------------------------------------------------------------------------------

def bench_methods(modes_auto: bool = False) -> dict:
    """Named methods for benchmarks/bench_labels.py: callables (case, prepared, seed) -> Outcome."""
    import sys

    bench = sys.modules.get("bench_labels") or sys.modules["__main__"]

    def make(factory):
        def run(case, prep, seed):
            cfg = bench.MmgpMethod().config(seed)
            kw = bench.sem_settings(cfg, prep.basis_kind)
            f = prep.feats
            t0 = time.perf_counter()
            m = factory(case.n_modes, kw).fit(f.X, f.Y, t=f.t, starts=f.starts, basis=f.basis)
            info = {"agreement": getattr(m, "agreement_", 1.0), "log_marginal": float(m.log_marginal_)}
            return bench.Outcome(m.disturbed_.astype(bool), m.p_disturbed_, m.labels_, time.perf_counter() - t0, info)

        run.seeded = True
        return run

    return {
        "robust": make(lambda K, kw: RobustStartSEM(K, **kw)),
        "det": make(lambda K, kw: DeterministicSEM(K, **kw)),
        "det_plain": make(lambda K, kw: DeterministicSEM(K, trim=(), start_cut=4.0, **kw)),
        "chains4": make(lambda K, kw: ChainSet(K, n_chains=4, **kw)),
        "chains4avg": make(lambda K, kw: ChainSet(K, n_chains=4, combine="average", **kw)),
        "robust_chains4": make(lambda K, kw: ChainSet(K, n_chains=4, chain_class=RobustStartSEM, **kw)),
    }


# ----------------------------------------------------------------------------------------------
# Deterministic E-step (prototype: MultimodalSEM's sampler swapped for a decoder)
# ----------------------------------------------------------------------------------------------

def smoothed_marginals(alpha: np.ndarray, A: np.ndarray, starts=(0,)) -> np.ndarray:
    """p(s_t | y_1:T) (T, S) from filtered ``alpha`` (T, S) alone, by the backward recursion
    p(s_t | y) = sum_s' p(s_t | s_{t+1} = s', y_1:t) p(s_{t+1} = s' | y)."""
    T, S = alpha.shape
    is_start = np.zeros(T + 1, bool)
    is_start[list(starts)] = True
    is_start[T] = True
    post = np.empty((T, S))
    for t in range(T - 1, -1, -1):
        if is_start[t + 1]:
            post[t] = alpha[t]
            continue
        joint = alpha[t][:, None] * A                      # (s_t, s_{t+1}) up to a column constant
        cond = joint / np.maximum(joint.sum(0, keepdims=True), 1e-300)
        post[t] = cond @ post[t + 1]
    return post / post.sum(1, keepdims=True)


def mpm_decode(alpha, A, rng, starts=(0,)) -> np.ndarray:
    """Drop-in for ``ffbs_sample``: the most probable state of each sample (no randomness)."""
    return smoothed_marginals(alpha, A, starts).argmax(1)


class DeterministicSEM(RobustStartSEM):
    """RobustStartSEM with hard EM: every sweep's labels are the posterior's most probable states,
    so the chain's answer depends on the seed only through support subsets of long logs."""

    def fit(self, X, Y, **kw):
        from . import sem as sem_module

        sampler = sem_module.ffbs_sample
        sem_module.ffbs_sample = mpm_decode
        try:
            return super().fit(X, Y, **kw)
        finally:
            sem_module.ffbs_sample = sampler
