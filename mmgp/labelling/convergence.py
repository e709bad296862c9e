"""When the stochastic EM stops: the per-sweep record and the convergence monitor.

Sampled labels keep flickering at the margins, so convergence is judged on trends over the last
``patience`` sweeps, then the posterior marginals of ``average_last`` further sweeps are averaged.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SweepRecord:
    sweep: int
    log_joint: float          # log p(Y, s) at the sampled labels
    log_marginal: float       # log p(Y) under the chain, given the sweep's likelihoods
    changed: float            # fraction of samples whose state changed
    n_disturbed: int
    mode_sizes: list
    seconds: float


class ConvergenceMonitor:
    """Decides, sweep by sweep, when to start averaging the posterior and when to stop.

    Converged when at least ``min_sweeps`` sweeps are done and, over the last ``patience`` sweeps,
    the sampled labels change in fewer than ``tol_changed`` of the samples on average and either
    the mean log joint stops rising compared with the ``patience`` sweeps before or fewer than a
    fifth of ``tol_changed`` change. After convergence (or ``max_sweeps``), the marginals (T, S)
    of ``average_last`` more sweeps are averaged.

    State: ``trace`` (list of SweepRecord), ``converged``, ``averaging`` (the sweeps now run are
    averaged; no hyperparameter refits then), ``posterior()`` (T, S) once done, ``best`` the sweep
    with the highest log marginal likelihood so far (its record, marginals and what the caller
    gave to :meth:`update` with it): an EM that does not converge ends there (:meth:`fall_back`).
    """

    def __init__(self, *, min_sweeps: int, max_sweeps: int, tol_changed: float, patience: int,
                 average_last: int):
        self.min_sweeps = min_sweeps
        self.max_sweeps = max_sweeps
        self.tol_changed = tol_changed
        self.patience = patience
        self.average_last = average_last
        self.trace: list[SweepRecord] = []
        self.converged = False
        self.averaging = False
        self._quiet = False
        self._post_sum: np.ndarray | None = None
        self._n_avg = 0
        self.best: tuple[SweepRecord, np.ndarray, object] | None = None
        self.fell_back = False

    def update(self, rec: SweepRecord, probs: np.ndarray, state: object = None, refit: bool = False) -> bool:
        """Record one sweep, its marginals (T, S) and the caller's ``state`` after it (kept while
        it is the best sweep); ``refit``: the sweep refitted the hyperparameters, so only it and
        the sweeps after it compete for the best (their log marginals share hyperparameters, which
        earlier sweeps had less optimised). True when the EM should stop."""
        self.trace.append(rec)
        if self.best is None or refit or rec.log_marginal > self.best[0].log_marginal:
            self.best = (rec, probs, state)
        if self._post_sum is None:
            self._post_sum = np.zeros_like(probs)
        if self.averaging:
            self._post_sum += probs
            self._n_avg += 1
            return self._n_avg >= self.average_last
        if len(self.trace) >= 2 * self.patience:
            self._quiet = self._labels_settled()
        if len(self.trace) >= self.min_sweeps and self._quiet:
            self.converged = True
            self.averaging = True
        elif len(self.trace) >= self.max_sweeps:
            self.averaging = True
        return False

    def _labels_settled(self) -> bool:
        # The mean log joint of the last `patience` sweeps no longer beats the mean of the
        # `patience` before by more than a small tolerance, and few labels move.
        lj = [r.log_joint for r in self.trace]
        w = self.patience
        now, before = np.mean(lj[-w:]), np.mean(lj[-2 * w:-w])
        flat = now - before <= 1e-3 * abs(before) + 1.0
        moved = np.mean([r.changed for r in self.trace[-w:]])
        # Once under a fifth of the tolerance move, the sampled log joint only wanders with the
        # draws (hundreds of nats on a long log while the labels barely move), so it is not waited
        # for.
        return bool(moved < self.tol_changed and (flat or moved < 0.2 * self.tol_changed))

    def abandon(self, probs: np.ndarray) -> None:
        """Stop now without converging; the posterior is the last sweep's marginals (T, S)."""
        self._post_sum, self._n_avg, self.averaging = np.array(probs, copy=True), 1, True

    def fall_back(self) -> object:
        """Where the sweeps did not converge (they cycle between labellings, each M-step undoing the
        last), end at the sweep whose parameters explain the log best, its log marginal
        likelihood the highest of the sweeps since the last hyperparameter refit (what EM
        climbs), rather than averaging the cycle's
        last sweeps: the posterior becomes that sweep's marginals. Returns the state given with it."""
        rec, probs, state = self.best
        self._post_sum, self._n_avg, self.fell_back = np.array(probs, copy=True), 1, True
        return state

    def posterior(self) -> np.ndarray:
        """The averaged marginals (T, S) of the sweeps after convergence."""
        return self._post_sum / max(self._n_avg, 1)
