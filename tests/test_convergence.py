"""When the EM stops and what it ends with: a sweep sequence that converges is averaged after
convergence; one that cycles ends at its sweep of highest log marginal likelihood (references
computed here from the sequence fed in)."""
from __future__ import annotations

import numpy as np

from mmgp.labelling.convergence import ConvergenceMonitor, SweepRecord
from mmgp.labelling.sem import MultimodalSEM


def _monitor(**kw):
    return ConvergenceMonitor(**{"min_sweeps": 3, "max_sweeps": 6, "tol_changed": 0.05, "patience": 2,
                                 "average_last": 2, **kw})


def _feed(monitor, marginals, changed, rng, refits=()):
    probs = []
    for i, (lm, ch) in enumerate(zip(marginals, changed)):
        p = rng.dirichlet(np.ones(2), size=5)
        probs.append(p)
        stop = monitor.update(SweepRecord(i, lm, lm, ch, 0, [5], 0.0), p, state=("state", i), refit=i in refits)
        if stop:
            break
    return probs


def test_a_cycling_em_ends_at_its_best_sweep():
    rng = np.random.default_rng(0)
    # labels keep changing by 40-50% (a two-sweep cycle): never converged, max_sweeps then averaging
    marginals = [100.0, 900.0, 300.0, 850.0, 200.0, 800.0, 150.0, 700.0]
    m = _monitor()
    probs = _feed(m, marginals, [0.45] * len(marginals), rng)
    assert not m.converged and len(m.trace) == 8           # 6 sweeps, then 2 averaged
    best = int(np.argmax(marginals))
    assert m.fall_back() == ("state", best)
    np.testing.assert_array_equal(m.posterior(), probs[best])
    assert m.fell_back and m.best[0].sweep == best


def test_only_sweeps_since_the_last_hyperparameter_refit_compete():
    rng = np.random.default_rng(2)
    marginals = [100.0, 900.0, 300.0, 850.0, 200.0, 800.0, 150.0, 700.0]
    m = _monitor()
    probs = _feed(m, marginals, [0.45] * len(marginals), rng, refits=(0, 2))
    best = 2 + int(np.argmax(marginals[2:]))                 # sweep 1's 900 came with older hyperparameters
    assert best == 3 and m.fall_back() == ("state", best)
    np.testing.assert_array_equal(m.posterior(), probs[best])


def test_a_converged_em_averages_the_sweeps_after_convergence():
    rng = np.random.default_rng(1)
    marginals = [500.0, 400.0, 400.0, 400.0, 400.0, 400.0]
    m = _monitor()
    probs = _feed(m, marginals, [0.3, 0.01, 0.01, 0.01, 0.01, 0.01], rng)
    assert m.converged and not m.fell_back
    # converged at the 4th sweep (2 x patience records, quiet); the next two are averaged
    np.testing.assert_allclose(m.posterior(), (probs[4] + probs[5]) / 2)


def test_the_sem_that_does_not_converge_keeps_its_best_sweep():
    rng = np.random.default_rng(1)
    t = np.arange(300) / 20.0
    x = 2.0 * np.sin(3.0 * t) + 0.3 * np.sin(7.1 * t)
    push = np.zeros(len(t))
    dist = np.zeros(len(t), bool)
    for a, n in [(25, 6), (70, 12), (130, 9), (190, 15), (250, 7)]:
        push[a:a + n], dist[a:a + n] = rng.choice([-1.0, 1.0]) * 0.7, True
    y = np.sin(1.5 * x) + push + 0.05 * rng.normal(size=len(t))
    # three sweeps cannot show convergence (it compares 2 x patience sweeps): the sweep limit ends it
    m = MultimodalSEM(1, disturbance=True, max_sweeps=3, min_sweeps=3, patience=3, seed=0).fit(
        x[:, None], y[:, None], t=t)
    lm = [r.log_marginal for r in m.trace_]
    # on a log this short the sweeps refit the hyperparameters at sweeps 0, 1, 2, 4, ... until the
    # sweep limit (3 sweeps: 0-2; then one averaged sweep, no refit): the best is taken from 2 on
    last_refit = max(i for i in (0, 1, 2, 4, 8, 16, 32) if i < 3)
    assert not m.converged_
    assert m.labels_sweep_ == last_refit + int(np.argmax(lm[last_refit:]))
    assert m.log_marginal_ == max(lm[last_refit:])
    assert m.disturbed_[dist].mean() >= 0.9 and m.disturbed_[~dist].mean() <= 0.05
