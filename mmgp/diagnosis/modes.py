"""Mode switches: does an effect that takes one of two values over time (a payload attached and
removed) predict the held-out residual better than one fixed value?

The two-mode model is a sticky two-state switching regression on what the selected physics
leaves, ``e_t = C_t theta_{s_t} + noise``, fitted by EM with the HMM of ``mmgp.labelling.hmm`` (the
one the multimodal learner uses). It is compared with the one-mode fit on held-out time blocks,
where the two-mode model may only use samples a filter memory earlier (an HMM ``lag``-step
predictive), so it cannot win by merely tracking the residual's autocorrelation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..labelling.estep import stretches
from ..labelling.hmm import forward_backward, transition_matrix
from ..physics.effects import Effect
from ..data.regression import solve_gram
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


def _fit_switching(C: np.ndarray, e: np.ndarray, w: np.ndarray, V: np.ndarray, n_iter: int = 25,
                   init: np.ndarray | None = None):
    """EM for e_t = C_t theta_{s_t} + noise, s_t a sticky two-state Markov chain.

    ``C`` (T, n, p) columns, ``e`` (T, n) residual, ``w`` (n,) inverse noise variances, ``V``
    (T, n) sample weights. Returns (theta (2, p), stay probability, posterior (T, 2)). Started
    from ``init`` (T,) 0/1 labels (the multimodal learner's modes: the inference ``mmgp train``
    makes) or, without them (or with one mode only), from a split of the time axis at the median
    of windowed single-state fits' first coefficient.
    """
    T, n, p = C.shape
    Wv = V * w[None, :]
    Gt = np.einsum("tj,tjp,tjq->tpq", Wv, C, C).reshape(T, p * p)
    ct = np.einsum("tj,tjp,tj->tp", Wv, C, e)

    def wls(g):
        return solve_gram((g @ Gt).reshape(p, p), g @ ct)

    if init is not None and 0 < np.mean(init) < 1:
        hi = np.asarray(init, dtype=float)
    else:
        # windowed fits of the first coefficient (the magnitude, e.g. the mass), split at their median
        edges = np.linspace(0, T, 9).astype(int)
        loc = np.array([wls(((np.arange(T) >= a) & (np.arange(T) < b)).astype(float))[0]
                        for a, b in zip(edges[:-1], edges[1:])])
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


def mode_switch_test(C: np.ndarray, e: np.ndarray, w: np.ndarray, V: np.ndarray, folds, lag: int = 1,
                     init: np.ndarray | None = None) -> dict:
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
        th2, stay, _ = _fit_switching(C[tr], e[tr], w, V[tr], n_iter=15, init=None if init is None else init[tr])
        P = transition_matrix(2, stay)
        alpha, _, _ = forward_backward(_loglik(C[te], e[te], Wv[te], th2), P, _EVEN)
        pred = np.full((len(te), 2), 0.5)
        if len(te) > lag:
            pred[lag:] = alpha[:-lag] @ np.linalg.matrix_power(P, max(lag, 1))
        mu = pred[:, 0, None] * (C[te] @ th2[0]) + pred[:, 1, None] * (C[te] @ th2[1])
        d.append(err1 - (Wv[te] * (e[te] - mu) ** 2).sum())
    d = np.array(d)
    th, stay, post = _fit_switching(C, e, w, V, init=init)
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


def _screen(cands, e_all, w, M, idx, init=None) -> list:
    """Two-mode fit of every candidate on all (thinned) samples: in-sample gain over one mode."""
    Wv = M[idx] * w[None, :]
    out = []
    for eff, C in cands:
        Cm, em = C[idx], e_all[idx]
        th1 = _wls(Cm, em, Wv)
        th2, _, post = _fit_switching(Cm, em, w, M[idx], n_iter=10, init=init)
        mu = post[:, 0, None] * (Cm @ th2[0]) + post[:, 1, None] * (Cm @ th2[1])
        out.append(((Wv * (em - Cm @ th1) ** 2).sum() - (Wv * (em - mu) ** 2).sum(), eff, C))
    return out


#: a mode holds the effect when its held-out gain over none is significant and at least this
#: share of the mode's held-out error without it (the materiality rule of ``reidentify``)
MIN_MODE_GAIN = 0.05


def _mode_presence(Gk: np.ndarray, ck: np.ndarray, yk: np.ndarray, nonneg, cones, alpha: float) -> np.ndarray:
    """(2,) bool: whether each mode holds the effect. Per time block k, the mode's fit on the
    other blocks against none (the effect at zero) on block k: the gain ``2 th.c_k - th'G_k th``
    from the blocks' sums ``Gk`` (2, K, p, p), ``ck`` (2, K, p) and ``yk`` (2, K) (weighted
    squares of the residual without the effect). A bootstrap interval alone would call a small
    bias that is the same in every block (a point mass linearised a little off) a payload."""
    from .fitting import cone_gram_fit

    out = []
    for m in range(2):
        G, c = Gk[m].sum(0), ck[m].sum(0)
        d = np.array([(lambda th: 2 * th @ ck[m, k] - th @ Gk[m, k] @ th)(
            cone_gram_fit(G - Gk[m, k], c - ck[m, k], nonneg, cones)) for k in range(Gk.shape[1])])
        out.append(signed_rank_p(d) < alpha and d.sum() >= MIN_MODE_GAIN * yk[m].sum())
    return np.array(out)


def _constrained_modes(eff, rm: dict, base: np.ndarray, C: np.ndarray, e: np.ndarray, w: np.ndarray,
                       V: np.ndarray, ctx, folds, *, alpha: float, n_boot: int = 200, seed: int = 0):
    """The two modes' coefficients refitted on their samples (posterior weights) with the
    effect's constraints (a mode without payload has mass 0, not a slightly negative one), as
    changes from ``base`` (2, p), block-bootstrap replicates of the modes' total coefficients
    (n_boot, 2, p) over the time blocks of ``folds``, and (2,) bool whether each mode's magnitude
    holds it (``_mode_presence`` at level ``alpha``); None when a mode is still not
    physically possible (e.g. its centre of mass beyond the robot's reach)."""
    from .fitting import cone_gram_fit, constraints

    atoms = list(eff.atoms())
    nonneg, cones = constraints([eff], atoms, list(range(len(atoms))), ctx)
    y = e + C @ base  # the residual without the effect's one-mode fit
    K = len(folds)
    Gk = np.zeros((2, K, len(atoms), len(atoms)))
    ck = np.zeros((2, K, len(atoms)))
    yk = np.zeros((2, K))
    for m in range(2):
        Wv = V * w[None, :] * rm["post"][:, m, None]
        for k, (_, te) in enumerate(folds):
            Gk[m, k] = np.einsum("tj,tjp,tjq->pq", Wv[te], C[te], C[te])
            ck[m, k] = np.einsum("tj,tjp,tj->p", Wv[te], C[te], y[te])
            yk[m, k] = np.einsum("tj,tj->", Wv[te], y[te] ** 2)
    total = np.array([cone_gram_fit(Gk[m].sum(0), ck[m].sum(0), nonneg, cones) for m in range(2)])
    if not all(eff.admissible(dict(zip(atoms, total[m])), ctx) for m in range(2)):
        return None
    counts = np.random.default_rng(seed).multinomial(K, np.full(K, 1.0 / K), size=n_boot).astype(float)
    boot = np.array([[cone_gram_fit(np.tensordot(c, Gk[m], 1), c @ ck[m], nonneg, cones) for m in range(2)]
                     for c in counts])
    return total - base, boot, _mode_presence(Gk, ck, yk, nonneg, cones, alpha)


def _stretch_centred(x: np.ndarray, Wv: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``x`` (T, n[, p]) minus its ``Wv``-weighted (T, n) mean over each unbroken stretch of
    ``labels`` (T,), per joint (and column)."""
    out = np.array(x, dtype=np.float64)
    for a, length in zip(*stretches(labels)):
        b = a + length
        wv = Wv[a:b].reshape(length, Wv.shape[1], *([1] * (x.ndim - 2)))
        out[a:b] -= (wv * x[a:b]).sum(0) / (wv.sum(0) + 1e-300)
    return out


def modes_differ_in_motion(C: np.ndarray, y: np.ndarray, w: np.ndarray, V: np.ndarray, labels: np.ndarray,
                           totals: np.ndarray, t: np.ndarray, f_c: float | None, n_folds: int,
                           alpha: float) -> bool:
    """Whether each mode's coefficients ``totals`` (2, p) predict that mode's own samples better
    than the other mode's do, on what varies within the mode's unbroken stretches (``labels``
    (T,) 0/1): ``y`` (T, n) the residual without the effect, ``C`` (T, n, p) its columns, both
    centred per stretch; ``w`` (n,) joint weights, ``V`` (T, n) valid equations. Held out over
    ``n_folds`` time blocks of the mode's samples (the mode's fit on the other blocks against the
    other mode's coefficients), one-sided signed-rank test at ``alpha`` per mode.

    Why within stretches: a payload's torque follows the pose, so where the robot moves within a
    mode the two modes' payloads predict differently; a push held at a held pose is a constant
    torque at a constant pose, which a stretch's mean takes whole, and which any second "payload"
    matches at that one pose (benchmarks/README.md, "a held push is not a payload")."""
    Wv = V * w[None, :]
    Cc, yc = _stretch_centred(C, Wv, labels), _stretch_centred(y, Wv, labels)
    for m in range(2):
        idx = np.flatnonzero(labels == m)
        if len(idx) < 2 * n_folds:
            return False
        d = []
        for tr, te in time_folds(len(idx), n_folds, t[idx], f_c):
            tr, te = idx[tr], idx[te]
            th = _wls(Cc[tr], yc[tr], Wv[tr])
            sse = [float((Wv[te] * (yc[te] - Cc[te] @ c) ** 2).sum()) for c in (totals[1 - m], th)]
            d.append(sse[0] - sse[1])
        if signed_rank_p(np.array(d)) >= alpha:
            return False
    return True


def find_mode_switch(cands, e_all: np.ndarray, w: np.ndarray, M: np.ndarray, t: np.ndarray, f_c: float | None,
                     base_coef: dict, ctx, *, alpha: float, n_folds: int, max_samples: int,
                     init: np.ndarray | None = None) -> ModeSwitch | None:
    """The mode switch the data supports, if any.

    ``cands``: list of (effect, columns (T, n, p)) that may switch; ``e_all`` (T, n) residual of
    the selected physics; ``w`` (n,) joint weights; ``M`` (T, n) valid equations; ``base_coef``
    atom -> coefficient of the selected physics fit (an effect not in it has zeros); ``init``
    (T,) 0/1 the multimodal learner's two modes, where the switching fits start. All
    candidates get an in-sample screen; the two with the largest gain get the held-out test at
    family-wise level ``alpha`` over every candidate; a candidate that passes is kept when its
    modes are physically possible (``_constrained_modes``) and differ where the robot moves within
    them (``modes_differ_in_motion``: a push held at one pose matches a second payload there).
    """
    T = len(t)
    step, lag = _thinning(T, t, f_c, max_samples)
    idx = np.arange(0, T, step)
    folds = time_folds(len(idx), n_folds, t[idx], f_c)
    init = None if init is None else np.asarray(init)[idx]
    tests = [(eff, C, mode_switch_test(C[idx], e_all[idx], w, M[idx], folds, lag=lag, init=init))
             for _, eff, C in sorted(_screen(cands, e_all, w, M, idx, init), key=lambda x: -x[0])[:2]]
    base = {eff: np.array([base_coef.get(a, 0.0) for a in eff.atoms()]) for eff, _ in cands}
    best = []
    for eff, C, rm in tests:
        if rm["p"] < alpha / len(cands):
            fit = _constrained_modes(eff, rm, base[eff], C[idx], e_all[idx], w, M[idx], ctx, folds,
                                     alpha=alpha / 2)
            if fit is not None and modes_differ_in_motion(
                    C[idx], e_all[idx] + C[idx] @ base[eff], w, M[idx], rm["post"].argmax(1), base[eff] + fit[0],
                    t[idx], f_c, len(folds), alpha / 2):
                best.append((eff, {**rm, "theta": fit[0], "boot": fit[1], "present": fit[2]}))
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
    from .fitting import intervals

    T = len(t)
    lab = rm["post"].argmax(1)[np.minimum(np.round(np.arange(T) / step).astype(int), n_thin - 1)]
    order = np.argsort([(base + rm["theta"][k])[0] for k in range(2)])
    lab = np.argsort(order)[lab]
    theta = rm["theta"][order]
    atoms = eff.atoms()
    per_mode = []
    for k in range(2):
        params, _ = eff.params(dict(zip(atoms, base + theta[k])), {})
        reps = [dict(zip(atoms, b)) for b in rm["boot"][:, order[k]]]
        per_mode.append({**eff.report_params(params, ctx), "fraction": float((lab == k).mean()),
                         "interval": intervals(eff, reps, params), "present": bool(rm["present"][order[k]])})
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


class ModeBody(Effect):
    """What a found mode switch adds while the other effects are chosen again: the switching
    link's ten inertial parameters (an attached body has its own inertia, which a point mass
    lacks), one set per mode in ``modes``, each acting on that mode's samples (``labels``).
    Not a contract effect (no name): the ``mode_switch`` and per-mode ``payload`` findings tell
    it."""

    scope = "mode"

    def __init__(self, index: int, labels: np.ndarray, modes):
        super().__init__(index)
        self.labels = np.asarray(labels)
        self.modes = list(modes)

    def atoms(self):
        return tuple(("mode", k, self.index, i) for k in self.modes for i in range(10))

    def columns(self, ctx):
        Y = ctx.link_regressor(self.index)
        return [(self.labels == k)[:, None] * Y[:, :, i] for k in self.modes for i in range(10)]

    def where(self, ctx):
        return {"link": ctx.link_names[self.index]}

    def affected_joints(self, ctx):
        return list(range(self.index + 1))
