"""A still joint is called worse than its mean only where the held-out blocks say so
(``stages.still_worse_p``, ``plausibility.fit_warnings``): checked against a brute-force fold
loop and against closed-form cases (a model off by a constant, a model exact up to noise)."""
from types import SimpleNamespace

import numpy as np

from mmgp.diagnosis import stages as st
from mmgp.diagnosis.plausibility import fit_warnings
from mmgp.diagnosis.selection import time_folds


def _prob(T=1000, n=2, seed=0, lowpass=lambda x: x):
    rng = np.random.default_rng(seed)
    tau = 3.0 + 0.1 * rng.standard_normal((T, n))
    M = (rng.random((T, n)) > 0.05).astype(float)
    t = np.arange(T) * 0.01
    return SimpleNamespace(tau=tau, M=M, lowpass=lowpass, folds=time_folds(T, 10, t, None))


def test_mean_fold_errors_match_a_brute_force_loop():
    prob = _prob()
    use = np.ones(len(prob.tau), bool)
    use[100:180] = False
    got = st.mean_fold_errors(prob, use)
    for k, (tr, te) in enumerate(prob.folds):
        for j in range(prob.tau.shape[1]):
            trs = [i for i in tr if use[i] and prob.M[i, j] > 0]
            tes = [i for i in te if use[i] and prob.M[i, j] > 0]
            c = sum(prob.tau[i, j] for i in trs) / len(trs)
            want = sum((prob.tau[i, j] - c) ** 2 for i in tes)
            assert np.isclose(got[k, j], want, rtol=1e-10)


def _fold_errors(prob, use, offset):
    """(K, n) held-out squared errors of a model predicting the true level 3 + offset."""
    out = np.zeros((len(prob.folds), prob.tau.shape[1]))
    for k, (_, te) in enumerate(prob.folds):
        te = te[use[te]]
        out[k] = (prob.M[te] * (prob.tau[te] - 3.0 - offset) ** 2).sum(0)
    return out


def test_a_model_off_by_a_constant_is_worse_and_one_exact_up_to_noise_is_not():
    prob = _prob(seed=1)
    use = np.ones(len(prob.tau), bool)
    nominal = _fold_errors(prob, use, 0.0)
    # off by half a noise sd on joint 0: each block's error grows by ~25% (closed form: 0.05^2
    # per sample against 0.1^2), every block the same way
    found = _fold_errors(prob, use, np.array([0.05, 0.0]))
    p = st.still_worse_p(prob, use, nominal, found, [0, 1], ["a", "b"])
    assert p["a"] < 1e-3
    # joint 1 exact: its errors are the noise's, against the worse of the exact level and the
    # blocks' training means, which no block can call worse
    assert p["b"] > 0.5


def test_fit_warnings_on_a_still_joint_follow_the_test_not_the_total():
    names = ["a", "b"]
    fit = {"nominal": {"nmse": {"a": 1.04, "b": 1.0}}, "with_physics": {"nmse": {"a": 1.09, "b": 1.0}},
           "still_joints": names}
    _, bad = fit_warnings({**fit, "still_worse_p": {"a": 0.2, "b": 1.0}}, names)
    assert bad == set()
    _, bad = fit_warnings({**fit, "still_worse_p": {"a": 0.001, "b": 1.0}}, names)
    assert bad == {"a"}
    # Bonferroni over the two still joints: 0.04 is not below 0.05 / 2
    _, bad = fit_warnings({**fit, "still_worse_p": {"a": 0.04, "b": 1.0}}, names)
    assert bad == set()
    # a moving joint keeps the plain rule
    _, bad = fit_warnings({**fit, "still_joints": ["b"], "still_worse_p": {"b": 1.0}}, names)
    assert bad == {"a"}
