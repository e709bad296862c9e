"""Mode switches: does an effect that takes one of two values over time (a payload attached and
removed) predict the held-out residual better than one fixed value?

The two-mode model is a sticky two-state switching regression on what the selected physics
leaves, ``e_t = C_t theta_{s_t} + noise``, fitted by EM with the HMM of ``mmgp.models.hmm`` (the
one the multimodal learner uses). It is compared with the one-mode fit on held-out time blocks,
where the two-mode model may only use samples a filter memory earlier (an HMM ``lag``-step
predictive), so it cannot win by merely tracking the residual's autocorrelation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..models.hmm import forward_backward, transition_matrix
from ..models.robust import solve_gram
from .selection import signed_rank_p, time_folds

_EVEN = np.array([0.5, 0.5])


def switching_posterior(ll: np.ndarray, stay: float) -> np.ndarray:
    """(T, 2) state marginals of a symmetric two-state chain (p(stay) = ``stay``, uniform start)
    given log-likelihoods ``ll`` (T, 2)."""
    return forward_backward(ll, transition_matrix(2, stay), _EVEN)[1]


def _wls(C: np.ndarray, e: np.ndarray, Wv: np.ndarray) -> np.ndarray:
    """One-mode weighted least squares: theta (p,) with e ~ C @ theta, weights ``Wv`` (T, n)."""
    return solve_gram(np.einsum("tj,tjp,tjq->pq", Wv, C, C), np.einsum("tj,tjp,tj->p", Wv, C, e))


def _loglik(C, e, Wv, th) -> np.ndarray:
    return np.stack([-0.5 * (Wv * (e - C @ th[k]) ** 2).sum(1) for k in range(2)], 1)


def _fit_switching(C: np.ndarray, e: np.ndarray, w: np.ndarray, V: np.ndarray, n_iter: int = 25):
    """EM for e_t = C_t theta_{s_t} + noise, s_t a sticky two-state Markov chain.

    ``C`` (T, n, p) columns, ``e`` (T, n) residual, ``w`` (n,) inverse noise variances, ``V``
    (T, n) sample weights. Returns (theta (2, p), stay probability, posterior (T, 2)). Started
    from a split of the time axis at the median of windowed single-state fits' first coefficient.
    """
    T, n, p = C.shape
    Wv = V * w[None, :]
    Gt = np.einsum("tj,tjp,tjq->tpq", Wv, C, C).reshape(T, p * p)
    ct = np.einsum("tj,tjp,tj->tp", Wv, C, e)

    def wls(g):
        return solve_gram((g @ Gt).reshape(p, p), g @ ct)

    # start: windowed fits of the first coefficient (the magnitude, e.g. the mass), split at their median
    edges = np.linspace(0, T, 9).astype(int)
    loc = np.array([wls(((np.arange(T) >= a) & (np.arange(T) < b)).astype(float))[0] for a, b in zip(edges[:-1], edges[1:])])
    hi = np.zeros(T)
    for (a, b), v in zip(zip(edges[:-1], edges[1:]), loc):
        hi[a:b] = float(v > np.median(loc))
    post = np.stack([1 - hi, hi], 1)
    stay = 1 - 1.0 / max(T / 4, 2)
    th = np.zeros((2, p))
    for _ in range(n_iter):
        th = np.array([wls(post[:, k]) for k in range(2)])
        post = switching_posterior(_loglik(C, e, Wv, th), stay)
        # expected switches from consecutive posteriors (a cheap, slightly low estimate)
        sw = np.abs(np.diff(post[:, 1])).sum()
        stay = float(np.clip(1 - (sw + 1) / T, 0.5, 1 - 1.0 / T))
    return th, stay, post


def mode_switch_test(C: np.ndarray, e: np.ndarray, w: np.ndarray, V: np.ndarray, folds, lag: int = 1) -> dict:
    """Held-out comparison of one versus two modes for the effect with columns ``C`` (T, n, p).

    For each time-block fold both models are fitted on the training part; on the test block the
    two-mode model predicts each sample with its state probabilities given the test block's
    samples at least ``lag`` steps earlier (HMM ``lag``-step predictive), so the comparison stays
    out of sample. ``lag`` should span the residual's correlation time (the low-pass filter's
    memory): with a one-step predictive any latent-state model wins on a smooth residual just
    by tracking its autocorrelation.
    Returns {"d": (K,) held-out weighted SSE one-mode minus two-mode, "p": one-sided signed-rank
    p-value, and the all-data fit: "theta" (2, p), "post" (T, 2), "stay"}.
    """
    Wv = V * w[None, :]
    d = []
    for tr, te in folds:
        th1 = _wls(C[tr], e[tr], Wv[tr])
        err1 = (Wv[te] * (e[te] - C[te] @ th1) ** 2).sum()
        th2, stay, _ = _fit_switching(C[tr], e[tr], w, V[tr], n_iter=15)
        P = transition_matrix(2, stay)
        alpha, _, _ = forward_backward(_loglik(C[te], e[te], Wv[te], th2), P, _EVEN)
        pred = np.full((len(te), 2), 0.5)
        if len(te) > lag:
            pred[lag:] = alpha[:-lag] @ np.linalg.matrix_power(P, max(lag, 1))
        mu = pred[:, 0, None] * (C[te] @ th2[0]) + pred[:, 1, None] * (C[te] @ th2[1])
        d.append(err1 - (Wv[te] * (e[te] - mu) ** 2).sum())
    d = np.array(d)
    th, stay, post = _fit_switching(C, e, w, V)
    return {"d": d, "p": signed_rank_p(d), "theta": th, "post": post, "stay": stay}


@dataclass
class ModeSwitch:
    """A found mode switch of ``effect``: ``labels`` (T,) int (0 = the mode with the smaller
    first coefficient, e.g. the lighter payload), ``theta`` (2, p) the modes' coefficients added
    to the one-mode fit ``base`` (p,), ordered like the labels, ``per_mode`` contract params of
    each mode (with "fraction" of the time), ``switch_times_s``, ``test`` (mode_switch_test's
    result), ``n_tested`` (effects the family-wise level covers), ``step`` (thinning)."""

    effect: object
    labels: np.ndarray
    theta: np.ndarray
    base: np.ndarray
    per_mode: list
    switch_times_s: list
    test: dict
    n_tested: int
    step: int


def _thinning(T: int, t: np.ndarray, f_c: float | None, max_samples: int) -> tuple[int, int]:
    """(step, lag): keep every step-th sample (about four per cutoff period, at most
    ``max_samples``), and predict a held-out sample from samples a filter memory (one cutoff
    period) earlier."""
    dt = float(np.median(np.diff(t)))
    step = max(1, int(np.floor(1.0 / (4.0 * f_c * dt)))) if f_c else 1
    step = max(step, int(np.ceil(T / max_samples)))
    lag = int(np.ceil((1.0 / f_c) / (step * dt))) if f_c else 1
    return step, lag


def _screen(cands, e_all, w, M, idx) -> list:
    """Two-mode fit of every candidate on all (thinned) samples: in-sample gain over one mode."""
    Wv = M[idx] * w[None, :]
    out = []
    for eff, C in cands:
        Cm, em = C[idx], e_all[idx]
        th1 = _wls(Cm, em, Wv)
        th2, _, post = _fit_switching(Cm, em, w, M[idx], n_iter=10)
        mu = post[:, 0, None] * (Cm @ th2[0]) + post[:, 1, None] * (Cm @ th2[1])
        out.append(((Wv * (em - Cm @ th1) ** 2).sum() - (Wv * (em - mu) ** 2).sum(), eff, C))
    return out


def _admissible(eff, rm: dict, base: np.ndarray, ctx) -> bool:
    """Both modes physically possible (e.g. masses non-negative, centres of mass within reach)."""
    return all(eff.admissible(dict(zip(eff.atoms(), base + rm["theta"][k])), ctx) for k in range(2))


def find_mode_switch(cands, e_all: np.ndarray, w: np.ndarray, M: np.ndarray, t: np.ndarray, f_c: float | None,
                     base_coef: dict, ctx, *, alpha: float, n_folds: int, max_samples: int) -> ModeSwitch | None:
    """The mode switch the data supports, if any.

    ``cands``: list of (effect, columns (T, n, p)) that may switch; ``e_all`` (T, n) residual of
    the selected physics; ``w`` (n,) joint weights; ``M`` (T, n) valid equations; ``base_coef``
    atom -> coefficient of the selected physics fit (an effect not in it has zeros). All
    candidates get an in-sample screen; the two with the largest gain get the held-out test at
    family-wise level ``alpha`` over every candidate.
    """
    T = len(t)
    step, lag = _thinning(T, t, f_c, max_samples)
    idx = np.arange(0, T, step)
    folds = time_folds(len(idx), n_folds, t[idx], f_c)
    tests = [(eff, C, mode_switch_test(C[idx], e_all[idx], w, M[idx], folds, lag=lag))
             for _, eff, C in sorted(_screen(cands, e_all, w, M, idx), key=lambda x: -x[0])[:2]]
    base = {eff: np.array([base_coef.get(a, 0.0) for a in eff.atoms()]) for eff, _ in cands}
    best = [(eff, rm) for eff, _, rm in tests
            if rm["p"] < alpha / len(cands) and _admissible(eff, rm, base[eff], ctx)]
    if not best:
        return None
    eff, rm = max(best, key=lambda x: x[1]["d"].mean())
    if eff.distal_tiebreak:
        se = np.std(rm["d"], ddof=1) / np.sqrt(len(rm["d"]))
        for e2, rm2 in sorted(best, key=lambda x: -x[0].index):
            # of indices the data cannot tell apart, the most distal
            if e2.index > eff.index and rm["d"].mean() - rm2["d"].mean() <= se:
                eff, rm = e2, rm2
                break
    return _mode_switch(eff, rm, base[eff], ctx, t, step, len(idx), len(cands))


def _mode_switch(eff, rm: dict, base: np.ndarray, ctx, t: np.ndarray, step: int, n_thin: int,
                 n_tested: int) -> ModeSwitch:
    T = len(t)
    lab = rm["post"].argmax(1)[np.minimum(np.round(np.arange(T) / step).astype(int), n_thin - 1)]
    order = np.argsort([(base + rm["theta"][k])[0] for k in range(2)])
    lab = np.argsort(order)[lab]
    theta = rm["theta"][order]
    per_mode = []
    for k in range(2):
        params, _ = eff.params(dict(zip(eff.atoms(), base + theta[k])), {})
        per_mode.append({**eff.report_params(params, ctx), "fraction": float((lab == k).mean())})
    switches = [float(t[i]) for i in np.flatnonzero(np.diff(lab) != 0) + 1]
    return ModeSwitch(eff, lab, theta, base, per_mode, switches, rm, n_tested, step)


def mode_prediction(ms: ModeSwitch, C: np.ndarray) -> np.ndarray:
    """(T, n) what the two modes add to the one-mode residual, sample by sample (by label)."""
    mu = np.zeros(C.shape[:2])
    for k in range(2):
        mu += (ms.labels == k)[:, None] * (C @ ms.theta[k])
    return mu


def near_switches(ms: ModeSwitch, t: np.ndarray, f_c: float | None, margin_s: float = 0.0) -> np.ndarray:
    """(T,) bool: within the low-pass filter's memory (plus one thinning step) of a switch,
    where the filtered residual mixes both modes, widened by ``margin_s`` (s: how far estimated
    accelerations smear the transient a switch causes)."""
    near = np.zeros(len(t), bool)
    dt = float(np.median(np.diff(t)))
    h = (int(round(0.5 / (f_c * dt))) if f_c else 0) + int(round(margin_s / dt))
    for i in np.flatnonzero(np.diff(ms.labels) != 0) + 1:
        near[max(0, i - h - ms.step):i + h + ms.step] = True
    return near
