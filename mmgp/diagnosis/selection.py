"""Choosing effects: forward selection on time-block cross-validation.

:class:`FoldGrams` holds the sufficient statistics of weighted least squares per fold and joint,
so that any subset of atom columns is fitted and scored on held-out blocks without touching the
samples again. :class:`ForwardCVSelector` adds effects one at a time while the best candidate's
paired held-out gain over the folds is significant (one-sided Wilcoxon signed-rank test,
Bonferroni over the candidates of the step); physical admissibility is the effects' own.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from sklearn.base import BaseEstimator

from ..data.regression import solve_gram


def time_folds(T: int, K: int, t: np.ndarray, f_c: float | None):
    """K contiguous time blocks of ``T`` samples (``mmgp.data.folds.time_block_folds``) with a
    gap of the low-pass filter's memory (two periods of the cutoff ``f_c`` Hz) plus a
    differentiator window each side, so a held-out block shares no filtered noise with training."""
    from ..data.folds import time_block_folds

    gap_s = 0.05 + (2.0 / f_c if f_c else 0.0)
    gap = int(max(0, round(gap_s / max(float(np.median(np.diff(t))), 1e-9))))
    return time_block_folds(T, K, gap=min(gap, T // (4 * K)))


def carried_folds(M: np.ndarray, K: int, t: np.ndarray, f_c: float | None):
    """``time_folds`` laid over the samples that carry an equation (``M`` (T, n): some joint's
    equation valid), as indices into all T samples. A block where every joint rests holds no
    equation: its held-out gain is exactly zero, the signed-rank test drops it, and a log that
    rests most of the time (poses held between moves) would be judged on a few blocks whose test
    cannot reach the level. Every sample carries one (or too few do for K blocks): ``time_folds``."""
    carry = np.flatnonzero((np.asarray(M) > 0).any(1))
    if len(carry) == len(t) or len(carry) < 4 * K:
        return time_folds(len(t), K, t, f_c)
    return [(carry[tr], carry[te]) for tr, te in time_folds(len(carry), K, t[carry], f_c)]


def signed_rank_p(d: np.ndarray) -> float:
    """One-sided p-value of "the paired fold differences ``d`` (K,) are centred above zero":
    Wilcoxon signed-rank test (exact for small K). Distribution-free: a real effect's gain
    varies a lot between time blocks (fast motion in some, slow in others), which makes a
    t test weak, but it is positive in nearly every block."""
    from scipy.stats import wilcoxon

    d = np.asarray(d, dtype=np.float64)
    scale = np.abs(d).max() if d.size else 0.0
    d = d[np.abs(d) > 1e-12 * scale] if scale > 0 else d[:0]
    if len(d) < 2:
        return 1.0
    return float(wilcoxon(d, alternative="greater").pvalue)


def paired_gains(e, before: np.ndarray, after: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(K,) paired held-out gains of effect ``e``: fold errors per joint ``before`` and ``after``
    (K, n) adding it, ``w`` (n,) joint weights. An effect acting on its own joint's torque alone
    (``e.own_joint``: friction, armature, a spring, a torque offset) is judged on that joint: the
    other joints move only through coefficients they share with it (the re-identified body), and
    their fold-to-fold noise would drown a gain the joint shows in every block
    (benchmarks/README.md, "sixth session: tuning history"). Any other effect on the joint-weighted sum."""
    if e.own_joint:
        return before[:, e.index] - after[:, e.index]
    return (before - after) @ w


def gain_p(e, before: np.ndarray, after: np.ndarray, w: np.ndarray) -> float:
    """One-sided signed-rank p-value of ``paired_gains``; 1.0 when the joint-weighted total
    held-out error does not fall (an effect judged on its own joint must not cost the others
    more than it gains there). An effect on its own joint may also show on the weighted sum:
    through the shared body it can help the other joints more than its own; both tests are made,
    the smaller p doubled (Bonferroni over the two)."""
    if float((before - after).sum(0) @ w) <= 0.0:
        return 1.0
    p = signed_rank_p(paired_gains(e, before, after, w))
    if e.own_joint and before.shape[1] > 1:
        # (on one joint the two are the same test)
        p = min(1.0, 2.0 * min(p, signed_rank_p((before - after) @ w)))
    return p


def _weighted_sums(Aw: np.ndarray, rw: np.ndarray, sw: np.ndarray, idx: np.ndarray):
    """Per joint over samples ``idx``: Gram (n, P, P), cross term (n, P), sum of squares (n,) and
    number of samples with non-zero weight (n,). ``Aw`` (n, T, P), ``rw`` (n, T) weighted."""
    n, _, P = Aw.shape
    G, c, y, m = np.empty((n, P, P)), np.empty((n, P)), np.empty(n), np.empty(n)
    for j in range(n):
        Aj = Aw[j, idx]
        rj = rw[j, idx]
        G[j] = Aj.T @ Aj
        c[j] = Aj.T @ rj
        y[j] = rj @ rj
        m[j] = (sw[idx, j] > 0).sum()
    return G, c, y, m


class FoldGrams:
    """Sufficient statistics of weighted least squares per fold and joint.

    ``A``: (T, n, P) atom columns, ``r``: (T, n) residual, ``use``: (T,) bool samples to use,
    ``folds``: list of (train_idx, test_idx), ``W``: optional (T, n) non-negative weights per
    sample and joint. Stores the all-data Gram ``Gall`` (n, P, P) and cross term ``call`` (n, P),
    per fold the training part's ``Gtr``/``ctr`` and the test block's ``Gte``/``cte``, its sum
    of squares ``yte`` (K, n) and test-sample counts per joint ``nte`` (K, n).
    """

    def __init__(self, A: np.ndarray, r: np.ndarray, use: np.ndarray, folds, W: np.ndarray | None = None):
        T, n, P = A.shape
        K = len(folds)
        self.K, self.n, self.P = K, n, P
        # per-sample, per-joint weights (0 drops a joint's equation at that sample)
        sw = np.ones((T, n)) if W is None else np.sqrt(np.asarray(W, dtype=np.float64))
        # per joint, weighted and contiguous in time: the fold sums below slice rows only
        Aw = np.ascontiguousarray(np.transpose(A * sw[:, :, None], (1, 0, 2)))
        rw = np.ascontiguousarray((r * sw).T)
        # what :meth:`extended` adds columns to (references, not copies)
        self._inputs = (A, r, use, folds, sw)
        self.Gall, self.call, _, _ = _weighted_sums(Aw, rw, sw, np.flatnonzero(use))
        self.Gte = np.zeros((K, n, P, P))
        self.cte = np.zeros((K, n, P))
        self.yte = np.zeros((K, n))
        self.Gtr = np.zeros((K, n, P, P))
        self.ctr = np.zeros((K, n, P))
        self.nte = np.zeros((K, n))
        for k, (tr, te) in enumerate(folds):
            self.Gte[k], self.cte[k], self.yte[k], self.nte[k] = _weighted_sums(Aw, rw, sw, te[use[te]])
            # train = all minus (test block and the gaps around it): only the short excluded
            # stretch is summed, so K folds cost about two full Gram matrices
            excl = np.ones(T, bool)
            excl[tr] = False
            Ge, ce, _, _ = _weighted_sums(Aw, rw, sw, np.flatnonzero(excl & use))
            self.Gtr[k], self.ctr[k] = self.Gall - Ge, self.call - ce

    def extended(self, S: Sequence[int], B: np.ndarray) -> "FoldGrams":
        """The statistics of atoms ``S`` followed by the columns of ``B`` (T, n, p), on the same
        samples, weights and folds: ``S``'s blocks are taken from these sums, only ``B``'s products
        are computed, on the joints where it is non-zero, every fold at once (a candidate searched
        over a grid costs a few products, not a Gram of the whole library)."""
        S, p = list(S), B.shape[2]
        s = len(S)
        out = FoldGrams.__new__(FoldGrams)
        out.K, out.n, out.P, out._inputs = self.K, self.n, s + p, None
        for name in ("Gall", "Gte", "Gtr"):
            G = getattr(self, name)
            new = np.zeros(G.shape[:-2] + (s + p, s + p))
            new[..., :s, :s] = G[..., S, :][..., :, S]
            setattr(out, name, new)
        for name in ("call", "cte", "ctr"):
            c = getattr(self, name)
            new = np.zeros(c.shape[:-1] + (s + p,))
            new[..., :s] = c[..., S]
            setattr(out, name, new)
        out.yte, out.nte = self.yte, self.nte
        K = self.K
        for j in np.flatnonzero(B.any(axis=(0, 2))):
            sums = self.border_sums(j, S, B[:, j])
            for G, c, blk in ((out.Gall[j][None], out.call[j][None], sums[:1]), (out.Gte[:, j], out.cte[:, j], sums[1:K + 1]),
                              (out.Gtr[:, j], out.ctr[:, j], sums[:1] - sums[K + 1:])):
                G[:, s:, :] = blk[:, :, :-1]
                G[:, :, s:] = np.swapaxes(blk[:, :, :-1], 1, 2)
                c[:, s:] = blk[:, :, -1]
        return out

    def border_sums(self, j: int, S: Sequence[int], Bj: np.ndarray) -> np.ndarray:
        """(1 + 2K, p, |S| + p + 1) joint ``j``'s sums of the products of new columns ``Bj`` (T, p)
        with atoms ``S``, with themselves and with the residual (last), weighted: over the samples
        used (row 0), each fold's test block (rows 1 to K), each fold's excluded stretch (rows K + 1
        to 2K: test block and gaps; a fold's training sums are row 0 less its row)."""
        S = list(S)
        ind, starts = self._indicators()
        X = np.concatenate([self._weighted_base(j, S), Bj * self._inputs[4][:, j, None], self._weighted_r(j)[:, None]],
                           axis=1)
        Bw = X[:, len(S):len(S) + Bj.shape[1]]
        if 64 * len(starts) <= len(X):
            # a few long runs of samples (time blocks): one product per run
            ends = np.append(starts[1:], len(X))
            runs = np.stack([Bw[a:b].T @ X[a:b] for a, b in zip(starts, ends)])
        else:
            runs = np.add.reduceat(Bw[:, :, None] * X[:, None, :], starts, axis=0)
        return np.tensordot(ind, runs, 1)

    def _indicators(self) -> tuple[np.ndarray, np.ndarray]:
        """The sums :meth:`__init__` makes, as 0/1 rows over runs of consecutive samples that
        every sum takes or leaves alike: (1 + 2K, R) rows (the samples used, each fold's test
        block, each fold's excluded stretch: test block and gaps) and the R runs' first samples
        (a time-block split has a few runs per fold, so a sum over T samples is one over R runs)."""
        if not hasattr(self, "_ind"):
            A, r, use, folds, sw = self._inputs
            ind = np.zeros((1 + 2 * self.K, len(use)))
            ind[0] = use
            for k, (tr, te) in enumerate(folds):
                ind[1 + k, te[use[te]]] = 1.0
                ind[1 + self.K + k] = use
                ind[1 + self.K + k, tr] = 0.0
            starts = np.concatenate([[0], np.flatnonzero((ind[:, 1:] != ind[:, :-1]).any(0)) + 1])
            self._ind, self._base = (ind[:, starts], starts), {}
        return self._ind

    def _weighted_base(self, j: int, S: list) -> np.ndarray:
        """(T, |S|) joint ``j``'s columns ``S``, weighted (kept for the next candidate on them)."""
        key = (j, tuple(S))
        if key not in self._base:
            A, sw = self._inputs[0], self._inputs[4]
            self._base = {key: A[:, j][:, S] * sw[:, j, None], **{k: v for k, v in self._base.items() if k[1] == key[1]}}
        return self._base[key]

    def _weighted_r(self, j: int) -> np.ndarray:
        return self._inputs[1][:, j] * self._inputs[4][:, j]

    def normal_equations(self, S: Sequence[int], w: np.ndarray, fold: int | None = None):
        """Joint-weighted normal equations (G (|S|, |S|), c (|S|,)) of atoms ``S`` on all data
        or on a fold's training part; ``w`` (n,) joint weights."""
        S = list(S)
        G, c = (self.Gall, self.call) if fold is None else (self.Gtr[fold], self.ctr[fold])
        return np.einsum("j,jpq->pq", w, G[:, S][:, :, S]), np.einsum("j,jp->p", w, c[:, S])

    def fit(self, S: Sequence[int], w: np.ndarray, fold: int | None = None) -> np.ndarray:
        """Weighted LS coefficients of atoms ``S`` on all data or on a fold's training part."""
        if not len(S):
            return np.zeros(0)
        return solve_gram(*self.normal_equations(S, w, fold))

    def cv_errors(self, S: Sequence[int], w: np.ndarray) -> np.ndarray:
        """Held-out sum of squared errors (K, n) of the model with atoms ``S``."""
        S = list(S)
        if not S:
            return self.yte.copy()
        # every fold's training fit at once (the search scores thousands of atom sets)
        G = np.einsum("j,kjpq->kpq", w, self.Gtr[:, :, S][:, :, :, S])
        c = np.einsum("j,kjp->kp", w, self.ctr[:, :, S])
        return self.test_errors(S, solve_gram(G, c))

    def test_errors(self, S: Sequence[int], thetas) -> np.ndarray:
        """Sum of squared errors (K, n) on each test block of atoms ``S`` with the coefficients
        ``thetas[k]`` (|S|,) fitted elsewhere for fold k (None or no atoms: the residual's own)."""
        S = list(S)
        if not S or thetas is None:
            return self.yte.copy()
        th = np.asarray(thetas, dtype=np.float64)
        Gs, cs = self.Gte[:, :, S][:, :, :, S], self.cte[:, :, S]
        return self.yte + ((Gs @ th[:, None, :, None])[..., 0] * th[:, None] - 2 * cs * th[:, None]).sum(-1)


def atom_indices(effects, index: dict) -> list[int]:
    """Column indices (``index``: atom key -> column) of the atoms of ``effects``, each once."""
    S: list[int] = []
    for e in effects:
        for a in e.atoms():
            if index[a] not in S:
                S.append(index[a])
    return S


@dataclass
class PathStep:
    effects: list  # list[Effect]
    cv_mean: float
    cv_folds: np.ndarray  # (K,) joint-weighted held-out error per fold
    cv_joint: np.ndarray  # (K, n) held-out error per fold and joint


@dataclass
class _Candidate:
    cv_mean: float
    effect: object
    cv_folds: np.ndarray
    p_value: float
    cv_joint: np.ndarray


class ForwardCVSelector(BaseEstimator):
    """Forward selection of effects with time-block CV and a multiplicity-corrected paired test.

    At each step every admissible candidate (one not yet chosen, whose model with the chosen
    effects is physically admissible on the full-data fit: ``Effect.admissible``) is scored by
    the paired held-out differences ``d_k`` (weighted squared error of the current model minus
    that of the current model plus the candidate, fold k). A candidate qualifies when the
    one-sided Wilcoxon signed-rank p-value of ``d`` is below ``alpha / m`` (Bonferroni over the
    ``m`` candidates tried at that step: the best of many noise columns would otherwise look
    significant by chance). The qualifying candidate with the smallest held-out error is added;
    the search stops when none qualifies or after ``max_steps`` effects (None: no limit).

    ``fit(effects, keys, grams, w, ctx, start=())``: ``effects`` the candidate list, ``keys`` the
    atom keys indexing the Gram matrices, ``w`` (n,) joint weights (inverse noise variance), ``ctx``
    the Context the effects judge admissibility in, ``start`` effects the model holds from the
    outset (the re-identified rigid body: the others are judged against it). Learned: ``path_`` (list of PathStep),
    ``chosen_step_``, ``selected_`` (effects), ``p_values_`` (signed-rank p-value of each added
    effect's gain, in order).
    """

    def __init__(self, alpha: float = 0.05, max_steps: int | None = None):
        self.alpha = alpha
        self.max_steps = max_steps

    def _candidates(self, effects, chosen, keys, index, grams, w, ctx, cur: np.ndarray) -> list[_Candidate]:
        S0 = atom_indices(chosen, index)
        out = []
        for e in effects:
            if e in chosen:
                continue
            new = [index[a] for a in e.atoms() if index[a] not in S0]
            if not new:
                continue  # nested in what is already chosen (e.g. Coulomb inside load-dependent)
            if any(not any(o.name == req and o.index == e.index for o in chosen) for req in e.requires):
                continue
            S = S0 + new
            coef = dict(zip((keys[i] for i in S), grams.fit(S, w)))
            if not all(o.admissible(coef, ctx) for o in chosen + [e]):
                continue
            ej = grams.cv_errors(S, w)
            ef = ej @ w
            out.append(_Candidate(float(ef.mean()), e, ef, gain_p(e, cur, ej, w), ej))
        return out

    @staticmethod
    def _pick(ok: list[_Candidate], crit: float, cur: np.ndarray, K: int, w: np.ndarray) -> _Candidate:
        best = min(ok, key=lambda c: c.cv_mean)
        e = best.effect
        if e.supersedes:
            # nested look-alikes (a spring contains an offset): keep the smaller effect when it
            # qualifies on its own and the larger is not significantly better
            for c in ok:
                if c.effect.index == e.index and c.effect.name in e.supersedes and \
                        gain_p(e, c.cv_joint, best.cv_joint, w) >= crit:
                    return c
        if e.distal_tiebreak:
            # among indices the data cannot tell apart (held-out error within one standard error
            # of the best one's gain: the classic 1-SE rule), report the most distal
            se = np.std(cur - best.cv_folds, ddof=1) / np.sqrt(K)
            for c in sorted(ok, key=lambda c: -c.effect.index):
                if type(c.effect) is type(e) and c.effect.index > e.index and c.cv_mean - best.cv_mean <= se:
                    return c
        return best

    def fit(self, effects, keys, grams: FoldGrams, w: np.ndarray, ctx, start=()) -> "ForwardCVSelector":
        index = {a: i for i, a in enumerate(keys)}
        start = list(start)
        ej = grams.cv_errors(atom_indices(start, index), w)
        e0 = ej @ w
        path = [PathStep(start, float(e0.mean()), e0, ej)]
        p_values = []
        max_steps = (self.max_steps or len(effects)) + len(start)
        while len(path[-1].effects) < max_steps:
            cand = self._candidates(effects, path[-1].effects, keys, index, grams, w, ctx, path[-1].cv_joint)
            crit = self.alpha / max(len(cand), 1)
            ok = [c for c in cand if c.p_value < crit]
            if not ok:
                break
            c = self._pick(ok, crit, path[-1].cv_folds, grams.K, w)
            p_values.append(c.p_value)
            path.append(PathStep(path[-1].effects + [c.effect], c.cv_mean, c.cv_folds, c.cv_joint))
        self.path_ = path
        self.chosen_step_ = len(path) - 1
        self.selected_ = list(path[-1].effects)
        self.p_values_ = p_values
        return self


def own_atoms(e, chosen, index: dict) -> list[int]:
    """Column indices that leave the model with ``e``: its atoms no other chosen effect holds,
    except an effect it extends (``e.requires``: load dependence leaves Coulomb friction)."""
    others = atom_indices([o for o in chosen if o is not e], index)
    return [index[a] for a in e.atoms() if index[a] not in others]


def own_gain(e, chosen, index: dict, grams: FoldGrams, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out errors (K, n) of the chosen model without ``e``'s own atoms and with them, and the
    paired gains (K,) (``paired_gains``: on ``e``'s joint when it acts on its own joint)."""
    S = atom_indices(chosen, index)
    drop = set(own_atoms(e, chosen, index))
    err_with = grams.cv_errors(S, w)
    err_wo = grams.cv_errors([i for i in S if i not in drop], w)
    return err_wo, err_with, paired_gains(e, err_wo, err_with, w)


def prune(chosen: list, keys, grams: FoldGrams, w: np.ndarray, alpha: float) -> tuple[list, list]:
    """Backward elimination: while some chosen effect's own paired held-out gain is not
    significant (one-sided signed-rank p >= ``alpha`` / number of effects that hold atoms of their
    own: each finding must carry its own weight), drop the least significant and re-test.
    Returns (kept effects, [(dropped effect, p-value)])."""
    index = {a: i for i, a in enumerate(keys)}
    chosen, dropped = list(chosen), []
    while chosen:
        tested = [(gain_p(e, *own_gain(e, chosen, index, grams, w)[:2], w), k, e) for k, e in enumerate(chosen)
                  if own_atoms(e, chosen, index)]
        if not tested:
            break
        p, _, worst = max(tested, key=lambda x: (x[0], x[1]))
        if p < alpha / len(tested):
            break
        # an effect dropped takes those that extend it along
        gone = [worst] + [o for o in chosen if o.index == worst.index and worst.name in o.requires]
        chosen = [o for o in chosen if o not in gone]
        dropped += [(o, p) for o in gone]
    return chosen, dropped


def extend_nested(chosen: list, library, keys, grams: FoldGrams, w: np.ndarray, ctx, alpha: float) -> list:
    """Nested extensions of chosen effects (an effect whose ``requires`` names a chosen effect
    on its index: load dependence of a found Coulomb friction), each added when its paired
    held-out gain over the chosen model is significant (one-sided signed-rank test, Bonferroni
    over the extensions tried) and the extended model physically admissible."""
    index = {a: i for i, a in enumerate(keys)}
    tries = [e for e in library if e not in chosen and e.requires and
             all(any(o.name == req and o.index == e.index for o in chosen) for req in e.requires)]
    if not tries:
        return list(chosen)
    S0 = atom_indices(chosen, index)
    cur = grams.cv_errors(S0, w)
    out = list(chosen)
    for e in tries:
        S = S0 + [index[a] for a in e.atoms() if index[a] not in S0]
        coef = dict(zip((keys[i] for i in S), grams.fit(S, w)))
        if all(o.admissible(coef, ctx) for o in chosen + [e]) and \
                gain_p(e, cur, grams.cv_errors(S, w), w) < alpha / len(tries):
            out.append(e)
    return out
