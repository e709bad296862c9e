"""Coupled transmissions: a family of candidates of their own, decided before the other effects.

A motor that turns with two joints (``mmgp.physics.effects.CoupledTransmission``: w = dq[k] +
c dq[m]) has a nonlinear parameter, the ratio c, searched over a grid of |c| from 0.2 to 5 (steps
of 22%, both signs; a ratio under 0.2 is friction of joint k with a trace on m, which the data
cannot tell from per-joint friction). Its friction on joint k and c times it on joint m looks
partly like friction on each joint, so a coupling is tried *in their place*: the candidate model
is the library less the rigid body (per-joint effects, payloads) less the friction and armature
of both joints, or of one of them, plus the coupling. One joint may keep its own: a coupled wrist
has a motor of its own on one joint besides the motor that turns with both (motor 5 turns with
joint 5 alone, motor 6 with joints 5 and 6), and a coupling tried in place of both joints'
friction then has to carry motor 5's as well and falls short of the family's level, where with
joint 5's own friction kept it passes. The candidates are joint pairs x ratios x these three
replaced sets, and it must beat the per-joint effects on held-out blocks (one-sided signed-rank test on the
joint-weighted sum, the weighted total not raised: ``selection.gain_p``) at the family-wise level
``alpha`` over this family's own candidates (Bonferroni). That alone passes misfit that three more
columns fit a little better. A coupled motor must also show what only it does (:func:`physical`),
each at the level ``alpha``: its loss acts on *both* joints (the held-out error falls on joint k
and on joint m, each tested alone), and it *dissipates* (its friction columns beat the same
candidate with its inertia column alone: an inertia term on two joints at a fixed ratio is also
what a rigid body's rotational inertia puts there). These tests only veto a candidate the family's
test passed, so the family-wise error stays within ``alpha`` without splitting it further. In a
family of its own, the candidates neither dilute the per-joint effects' level nor meet a level set
by the library's size; per-joint friction that a coupling only mimics (friction on joints 2 and 3 of an
arm) keeps its place. It is decided before the robust fit, the push scan and the selection, which
would otherwise read a coupling as per-joint misfit: as outliers of the robust fit (a quarter of a
simulated UR5 wrist's samples weighted down) and as pushes. A coupling taken is an effect the
selection starts from, kept only while its own held-out gain stays significant (``prune``).

The ratio of the best candidate is refined on a fine grid (least weighted training error, the
coupling's magnitudes non-negative), with a block-bootstrap percentile interval over the time blocks.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..physics.effects import CoupledTransmission, build_atoms
from ..data.regression import solve_gram
from .fitting import LEVEL, N_BOOT, cone_gram_fit, constraints
from .selection import FoldGrams, atom_indices, gain_p, signed_rank_p

#: |ratio| candidates: 0.2 to 5 in 16 geometric steps (22% apart); each sign
RATIO_MAGNITUDES = 0.2 * 25.0 ** (np.arange(17) / 16)
#: per-joint effects a coupling of two joints stands in for
REPLACED = ("coulomb_friction", "viscous_friction", "load_dependent_friction", "armature")
#: ratios of the refinement, over two grid steps either side of the best grid ratio
FINE = 33


@dataclass
class Tried:
    """A candidate coupling: the effect, the chosen effects it keeps (``base``, atoms ``S``), its
    held-out errors (K, n) and p-value against the chosen model."""

    effect: CoupledTransmission
    base: list
    S: list
    cv_joint: np.ndarray
    p_value: float


def pairs(chosen, done=()) -> list[tuple[int, int]]:
    """Joint pairs (k < m) with per-joint friction or armature chosen on both, less ``done``."""
    js = sorted({e.index for e in chosen if e.name in REPLACED})
    return [(k, m) for i, k in enumerate(js) for m in js[i + 1:] if (k, m) not in done]


def columns(prob, ctx, e) -> np.ndarray:
    """(T, n, 3) low-passed columns of ``e``, as the library's (the filter acts on each channel
    alone: only the coupling's two joints, the others' columns are zero)."""
    B = np.stack(e.columns(ctx), axis=2)
    j = e.affected_joints(ctx)
    B[:, j] = prob.lowpass(B[:, j])
    return B


def _fit(g: FoldGrams, keys, S, e, ctx, w) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit of atoms ``S`` and ``e``'s on all data of ``g``, ``e``'s magnitudes non-negative;
    returns (coefficients, G, c) of the joint-weighted normal equations."""
    ext = list(keys) + list(e.atoms())
    nonneg, _ = constraints([e], ext, list(S) + list(range(len(keys), len(ext))), ctx)
    G, c = g.normal_equations(list(range(g.P)), w)
    return cone_gram_fit(G, c, nonneg), G, c


class Bordered:
    """The joint-weighted fits and held-out errors of the atoms ``S`` of ``grams`` (or a subset of
    them) plus a candidate's columns, for many candidates: ``S``'s sums weighted over the joints
    once, each candidate's products with them computed on its own joints only
    (``FoldGrams.border_sums``); the numbers of ``grams.extended(S, B)``'s ``fit`` and ``cv_errors``
    without copying the library's sums for every candidate. ``w`` (n,) joint weights."""

    def __init__(self, grams: FoldGrams, S, w: np.ndarray):
        self.g, self.S, self.w = grams, list(S), w
        S = self.S
        self.Gall = np.einsum("j,jpq->pq", w, grams.Gall[:, S][:, :, S])
        self.call = np.einsum("j,jp->p", w, grams.call[:, S])
        self.Gtr = np.einsum("j,kjpq->kpq", w, grams.Gtr[:, :, S][:, :, :, S])
        self.ctr = np.einsum("j,kjp->kp", w, grams.ctr[:, :, S])
        self.Gte, self.cte = grams.Gte[:, :, S][:, :, :, S], grams.cte[:, :, S]

    def products(self, B: np.ndarray) -> dict:
        """Joint -> ``border_sums`` of the new columns ``B`` (T, n, p), on the joints where they act."""
        return {j: self.g.border_sums(j, self.S, B[:, j]) for j in np.flatnonzero(B.any(axis=(0, 2)))}

    def _system(self, G0, c0, blk, at):
        """Normal equations (..., a + p, a + p), (..., a + p) of atoms ``at`` (places in S) plus the
        new columns: ``G0``, ``c0`` the atoms' own, ``blk`` (..., p, |S| + p + 1) the new columns' sums."""
        s, a, p = len(self.S), len(at), blk.shape[-2]
        cols = list(at) + list(range(s, s + p))
        G = np.zeros(blk.shape[:-2] + (a + p, a + p))
        G[..., :a, :a] = G0[..., at, :][..., :, at]
        G[..., a:, :] = blk[..., cols]
        G[..., :a, a:] = np.swapaxes(blk[..., at], -1, -2)
        return G, np.concatenate([c0[..., at], blk[..., -1]], axis=-1)

    def fit(self, prod: dict, at) -> np.ndarray:
        """(a + p,) coefficients on all data of atoms ``at`` and the new columns (``prod``)."""
        blk = sum(self.w[j] * x[0] for j, x in prod.items())
        return solve_gram(*self._system(self.Gall, self.call, blk, at))

    def cv_errors(self, prod: dict, at) -> np.ndarray:
        """Held-out sums of squared errors (K, n) of atoms ``at`` and the new columns (``prod``)."""
        K, s, a = self.g.K, len(self.S), len(at)
        blk = sum(self.w[j] * (x[0] - x[K + 1:]) for j, x in prod.items())
        th = solve_gram(*self._system(self.Gtr, self.ctr, blk, at))
        ts, tn = np.zeros((K, s)), th[:, a:]
        ts[:, at] = th[:, :a]
        err = self.g.yte + ((self.Gte @ ts[:, None, :, None])[..., 0] * ts[:, None] - 2 * self.cte * ts[:, None]).sum(-1)
        for j, x in prod.items():
            te = x[1:K + 1]
            err[:, j] += (np.einsum("kp,kpq,kq->k", tn, te[:, :, s:-1], tn) - 2 * np.einsum("kp,kp->k", tn, te[:, :, -1])
                          + 2 * np.einsum("kp,kpq,kq->k", tn, te[:, :, :s], ts))
        return err


def try_pair(prob, ctx, grams: FoldGrams, chosen, keys, k: int, m: int, w, cur) -> list[Tried]:
    """Every ratio of the grid for joints (k, m) and every replaced set (both joints, k alone, m
    alone): the model ``chosen`` less those joints' per-joint friction and armature, plus the
    coupling; ``cur`` (K, n) the model's held-out errors. The coupling's magnitudes must be
    non-negative (the rest is the library, a nuisance model here)."""
    index = {a: i for i, a in enumerate(keys)}
    S_all = atom_indices(chosen, index)
    variants = []  # (kept effects, their atoms, the atoms' places in S_all)
    for replaced in ((k, m), (k,), (m,)):
        base = [e for e in chosen if not (e.name in REPLACED and e.index in replaced)]
        S = atom_indices(base, index)
        variants.append((base, S, [S_all.index(i) for i in S]))
    # the three variants' sums are blocks of one: the coupling's products computed once per ratio
    sc = Bordered(grams, S_all, w)
    out = [[] for _ in variants]  # per replaced set, every ratio
    for c in np.concatenate([RATIO_MAGNITUDES, -RATIO_MAGNITUDES]):
        e = CoupledTransmission(k, m, c)
        prod = sc.products(columns(prob, ctx, e))
        for (base, S, at), tried in zip(variants, out):
            coef = dict(zip([keys[i] for i in S] + list(e.atoms()), sc.fit(prod, at)))
            ej = sc.cv_errors(prod, at)
            ok = e.admissible(coef, ctx)
            tried.append(Tried(e, base, S, ej, gain_p(e, cur, ej, w) if ok else 1.0))
    return [t for tried in out for t in tried]


def refine(prob, ctx, grams: FoldGrams, best: Tried, keys, w, *, seed: int = 0) -> CoupledTransmission:
    """The best candidate with its ratio at the least weighted training error on :data:`FINE`
    ratios within two grid steps of it (same sign), and the ratio's block-bootstrap percentile
    interval (blocks resampled with replacement, the ratio chosen again in each replicate; an
    interval reaching the searched span's end is cut there). Returned with |ratio| <= 1."""
    e0 = best.effect
    i = int(np.argmin(np.abs(RATIO_MAGNITUDES - abs(e0.ratio))))
    lo, hi = RATIO_MAGNITUDES[max(i - 2, 0)], RATIO_MAGNITUDES[min(i + 2, len(RATIO_MAGNITUDES) - 1)]
    fine = np.sign(e0.ratio) * np.geomspace(lo, hi, FINE)
    effects = [CoupledTransmission(e0.index, e0.coupled, c) for c in fine]
    gs = [grams.extended(best.S, columns(prob, ctx, e)) for e in effects]

    def error(th, G, c):
        return th @ G @ th - 2 * c @ th  # weighted squared error less the residual's own sum

    pick = int(np.argmin([error(*_fit(g, keys, best.S, e, ctx, w)) for g, e in zip(gs, effects)]))
    # per fine ratio, each block's joint-weighted sums; a replicate weights the blocks by its draw
    # (least squares there: the non-negative fit 33 x 200 times is what the search would cost)
    Gk = [np.einsum("j,kjpq->kpq", w, g.Gte) for g in gs]
    ck = [np.einsum("j,kjp->kp", w, g.cte) for g in gs]
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(grams.K, np.full(grams.K, 1.0 / grams.K), size=N_BOOT).astype(float)
    reps = []
    for m in counts:
        errs = []
        for G_, c_ in zip(Gk, ck):
            G, c = np.tensordot(m, G_, 1), m @ c_
            errs.append(error(solve_gram(G, c), G, c))
        reps.append(fine[int(np.argmin(errs))])
    ci = [float(x) for x in np.percentile(reps, [50 * (1 - LEVEL), 50 * (1 + LEVEL)])]
    return CoupledTransmission(e0.index, e0.coupled, float(fine[pick]), ci).canonical()


def pair_gain(t: Tried, cur: np.ndarray) -> float:
    """The held-out gain of candidate ``t`` on its two joints: one less its error there over what
    the context ``cur`` (K, n) leaves there."""
    j = [t.effect.index, t.effect.coupled]
    return 1.0 - float(t.cv_joint[:, j].sum() / max(cur[:, j].sum(), 1e-300))


def joint_p(t: Tried, cur: np.ndarray) -> float:
    """The larger of the one-sided signed-rank p-values of candidate ``t``'s held-out gains on its
    joint k and on its joint m over the chosen model's errors ``cur`` (K, n)."""
    e = t.effect
    return max(signed_rank_p(cur[:, j] - t.cv_joint[:, j]) for j in (e.index, e.coupled))


def friction_p(prob, ctx, grams: FoldGrams, t: Tried, w) -> float:
    """``gain_p`` of candidate ``t`` over the same model with the coupling's inertia column alone
    (its friction columns' own held-out gain)."""
    g = grams.extended(t.S, columns(prob, ctx, t.effect)[:, :, 2:])  # (columns: Coulomb, viscous, inertia)
    return gain_p(t.effect, g.cv_errors(list(range(g.P)), w), t.cv_joint, w)


def physical(prob, ctx, grams: FoldGrams, t: Tried, cur, w, alpha: float) -> bool:
    """Whether candidate ``t`` shows a coupled motor's signature at level ``alpha``: lower held-out
    error on each of its joints, and a significant gain from its friction (module docstring)."""
    return joint_p(t, cur) < alpha and friction_p(prob, ctx, grams, t, w) < alpha


def search(prob, ctx, grams: FoldGrams, chosen, keys, w, *, alpha: float, done=(), seed: int = 0):
    """The best coupling that beats the chosen model at the family's level and is
    :func:`physical` at ``alpha``, or None; and the search's evidence. ``done``: pairs already
    searched and taken."""
    cand = pairs(chosen, done)
    if not cand:
        return None, {}
    cur = grams.cv_errors(atom_indices(chosen, {a: i for i, a in enumerate(keys)}), w)
    tried = [t for k, m in cand for t in try_pair(prob, ctx, grams, chosen, keys, k, m, w, cur)]
    level = alpha / len(tried)
    best = min(tried, key=lambda t: t.p_value)
    ev = {"pairs": [list(p) for p in cand], "candidates": len(tried), "level": level,
          "best_p_value": best.p_value, "best": f"{best.effect.index}-{best.effect.coupled} x {best.effect.ratio:.3g}",
          "best_pair_gain": pair_gain(best, cur), "best_joint_p_value": joint_p(best, cur),
          "best_friction_p_value": friction_p(prob, ctx, grams, best, w)}
    # the least held-out error among the candidates passing every test (the costlier test last)
    ok = sorted((t for t in tried if t.p_value < level), key=lambda t: float((t.cv_joint @ w).mean()))
    best = next((t for t in ok if physical(prob, ctx, grams, t, cur, w, alpha)), None)
    if best is None:
        return None, ev
    e = refine(prob, ctx, grams, best, keys, w, seed=seed)
    gain = 1 - float((best.cv_joint @ w).sum() / max((cur @ w).sum(), 1e-300))
    ev.update(p_value=best.p_value, joint_p_value=joint_p(best, cur), friction_p_value=friction_p(prob, ctx, grams, best, w),
              held_out_gain=gain, pair=sorted((e.index, e.coupled)),
              replaces=[f"{o.name}@{o.index}" for o in chosen if o not in best.base])
    return (e, best.base), ev


def find_couplings(prob, weights: np.ndarray, w: np.ndarray, *, alpha: float, seed: int = 0):
    """Couplings in the context of the library less the rigid body (friction, armature, springs,
    offsets on every joint, payloads: with the body, a time-block fit of the whole library
    extrapolates worst, many times the coupling's held-out error; without the payloads, a
    payload was taken for a shoulder coupling) on sample
    weights ``weights`` (T, n), joint weights ``w`` (n,): each found one joins the context and the
    pairs left are searched again. Returns (the problem with the couplings in its library, the
    couplings, the evidence of each search)."""
    ctx, found, evidence, done = prob.ctx, [], [], set()
    context = [e for e in prob.library if e.scope != "model" and not e.own_family]
    while True:
        keys, A = build_atoms(context + found, ctx)
        grams = FoldGrams(prob.lowpass(A), prob.r, np.ones(len(prob.t), bool), prob.folds, W=weights)
        hit, ev = search(prob, ctx, grams, context + found, keys, w, alpha=alpha, done=done, seed=seed)
        if ev:
            evidence.append(ev)
        if hit is None:
            return dataclasses.replace(prob, library=list(prob.library) + found), found, evidence
        found.append(hit[0])
        done.add(tuple(sorted((hit[0].index, hit[0].coupled))))


def motor_rest_masks(prob, couplings, *, rest_factor: float):
    """The problem with each coupling's joints' equations also left out where its motor rests
    (w within ``rest_factor`` v_w of zero, ``separation.valid_mask``): a stuck coupled motor holds
    a set-valued friction on both joints, as a stuck joint does on its own, and the push scan would
    otherwise read it as a push."""
    from .separation import valid_mask

    M, M_scan, ctx = prob.M.copy(), prob.M_scan.copy(), prob.ctx
    for e in couplings:
        k, m, c = e.index, e.coupled, e.ratio
        w = (ctx.dq[:, k] + c * ctx.dq[:, m])[:, None]
        v = np.array([np.hypot(ctx.v_s[k], c * ctx.v_s[m])])
        for mask, kw in ((M, {}), (M_scan, {"min_rest_periods": 0.0})):
            mask[:, [k, m]] *= valid_mask(w, v, prob.t, prob.f_c, factor=rest_factor, **kw)
    return dataclasses.replace(prob, M=M, M_scan=M_scan)
