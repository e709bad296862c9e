"""The chosen effects refitted, their uncertainty, and the evidence each finding carries.

:func:`fit_physics` refits the chosen effects by non-negative least squares (magnitudes are
non-negative), moving linearisation points (a payload's centre of mass) to the fit. Uncertainty
is a *block bootstrap* over the cross-validation's time blocks (:func:`block_bootstrap`): the
blocks are resampled with replacement and the model refitted from their sufficient statistics,
which is honest under time-correlated residuals and costs one small solve per replicate; every
parameter gets a percentile interval (:func:`parameter_intervals`). :func:`effect_findings`
turns each chosen effect into a contract finding with its own held-out evidence.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..physics.context import Context
from .selection import FoldGrams, atom_indices, gain_p, own_gain

#: bootstrap replicates and the interval's coverage
N_BOOT = 200
LEVEL = 0.95


def nnls_gram(G: np.ndarray, c: np.ndarray, nonneg: np.ndarray) -> np.ndarray:
    """min th' G th - 2 c' th with th[nonneg] >= 0, via a Cholesky factor and lsq_linear."""
    from scipy.optimize import lsq_linear

    P = len(c)
    if P == 0:
        return np.zeros(0)
    reg = 1e-10 * max(np.diag(G).max(), 1e-300)
    L = np.linalg.cholesky(G + reg * np.eye(P))
    b = np.linalg.solve(L, c)
    lo = np.where(nonneg, 0.0, -np.inf)
    return lsq_linear(L.T, b, bounds=(lo, np.full(P, np.inf)), method="bvls").x


def cone_gram_fit(G: np.ndarray, c: np.ndarray, nonneg: np.ndarray, cones=()) -> np.ndarray:
    """:func:`nnls_gram` with second-order cones: each ``(i_mass, [i_hx, i_hy, i_hz], radius)`` of
    ``cones`` requires ``|h| <= radius * m`` (a point mass's centre within ``radius`` of its
    frame: a mass of zero has no first moment). Solved by cvxpy only when the bounded solution
    leaves a cone."""
    th = nnls_gram(G, c, nonneg)
    if all(np.linalg.norm(th[h]) <= r * th[m] * (1 + 1e-9) + 1e-12 for m, h, r in cones):
        return th
    import cvxpy as cp

    P = len(c)
    d = np.sqrt(np.clip(np.diag(G), 1e-300, None))
    Gs = G / np.outer(d, d) + 1e-10 * np.eye(P)
    L = np.linalg.cholesky(Gs)
    z = np.linalg.solve(L, c / d)
    y = cp.Variable(P)
    x = cp.multiply(1.0 / d, y)
    cons = [x[np.flatnonzero(nonneg)] >= 0] if nonneg.any() else []
    cons += [cp.SOC(r * x[m], x[list(h)]) for m, h, r in cones]
    cp.Problem(cp.Minimize(cp.sum_squares(L.T @ y - z)), cons).solve(solver=cp.CLARABEL)
    return np.asarray(y.value) / d if y.value is not None else th


@dataclass(frozen=True)
class PhysicsFit:
    """The chosen effects refitted: atoms ``S`` (indices into ``keys``) with coefficients
    ``coef`` (|S|,), bootstrap replicates ``boot`` (B, |S|) and their covariance ``cov``;
    ``grams`` of ``A`` in ``ctx``; ``w`` (n,) joint weights; ``weights`` (T, n) the robust sample
    weights of the fit; ``extra``: coefficients beyond the atoms (the re-identified body's full
    parameter change, ``("pi", i)``)."""

    ctx: Context
    keys: list
    A: np.ndarray
    grams: FoldGrams
    chosen: list
    S: list
    coef: np.ndarray
    boot: np.ndarray
    w: np.ndarray
    weights: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    @property
    def cov(self) -> np.ndarray:
        return np.cov(self.boot.T).reshape(len(self.S), len(self.S)) if len(self.boot) > 1 \
            else np.zeros((len(self.S), len(self.S)))

    def coefficients(self) -> dict:
        """atom key -> fitted coefficient (and the ``extra`` ones)."""
        return {**{self.keys[i]: float(v) for i, v in zip(self.S, self.coef)}, **self.extra}

    def residual(self, r: np.ndarray) -> np.ndarray:
        """(T, n) what the fitted effects leave of ``r``."""
        return r - (self.A[:, :, self.S] @ self.coef if self.S else 0.0)

    def with_coefficients(self, coef: dict) -> "PhysicsFit":
        """A copy with the atoms' coefficients (and extra entries) taken from ``coef``."""
        new = np.array([coef.get(self.keys[i], v) for i, v in zip(self.S, self.coef)])
        extra = {k: v for k, v in coef.items() if k not in set(self.keys)}
        return dataclasses.replace(self, coef=new, extra=extra)


def constraints(effects, keys: list, S: list, ctx) -> tuple[np.ndarray, list]:
    """The chosen ``effects``' constraints on atoms ``S`` (indices into ``keys``): non-negative
    atoms (|S|,) bool and cones with positions into ``S``."""
    pos = {keys[i]: k for k, i in enumerate(S)}
    nonneg = np.array([any(keys[i] in e.nonneg for e in effects) for i in S], bool)
    cones = [(pos[m], [pos[a] for a in h], r) for e in effects for m, h, r in e.cones(ctx)]
    return nonneg, cones


def block_bootstrap(grams: FoldGrams, S: list, w: np.ndarray, nonneg: np.ndarray, cones=(), *,
                    n_boot: int = N_BOOT, seed: int = 0) -> np.ndarray:
    """(n_boot, |S|) coefficients refitted on the time blocks resampled with replacement (each
    block's Gram and cross term weighted by how often it was drawn)."""
    if not S:
        return np.zeros((n_boot, 0))
    rng = np.random.default_rng(seed)
    K = grams.K
    Gk = np.einsum("j,kjpq->kpq", w, grams.Gte[:, :, S][:, :, :, S])
    ck = np.einsum("j,kjp->kp", w, grams.cte[:, :, S])
    counts = rng.multinomial(K, np.full(K, 1.0 / K), size=n_boot).astype(float)
    return np.array([cone_gram_fit(np.tensordot(m, Gk, 1), m @ ck, nonneg, cones) for m in counts])


def fit_physics(prob, lib, grams: FoldGrams, chosen: list, w: np.ndarray, use: np.ndarray, *,
                relinearise: int = 3, seed: int = 0) -> PhysicsFit:
    """Non-negative least squares of the chosen effects on samples ``use``, with ``relinearise``
    rounds for linearised effects (a payload's point-mass inertia at its fitted centre of mass),
    and a block bootstrap over the folds for the uncertainty."""
    ctx, keys, A = lib.ctx, lib.keys, lib.A
    S = atom_indices(chosen, {a: i for i, a in enumerate(keys)})
    nonneg, cones = constraints(chosen, keys, S, ctx)
    coef = cone_gram_fit(*grams.normal_equations(S, w), nonneg, cones)
    for _ in range(relinearise if any(e.linearised for e in chosen) else 0):
        fitted = {keys[i]: v for i, v in zip(S, coef)}
        for e in chosen:
            ctx = e.relinearise(fitted, ctx)
        keys, A = prob.atoms(ctx)
        grams = FoldGrams(A, prob.r, use, prob.folds, W=prob.M)
        coef = cone_gram_fit(*grams.normal_equations(S, w), nonneg, cones)
    boot = block_bootstrap(grams, S, w, nonneg, cones, seed=seed)
    return PhysicsFit(ctx, keys, A, grams, list(chosen), S, coef, boot, w, lib.weights)


def _flatten(params, prefix=()) -> dict:
    """{path: float} of nested params (dicts and lists of numbers)."""
    if isinstance(params, dict):
        return {k: v for key, sub in params.items() for k, v in _flatten(sub, prefix + (key,)).items()}
    if isinstance(params, (list, tuple)):
        return {k: v for i, sub in enumerate(params) for k, v in _flatten(sub, prefix + (i,)).items()}
    return {prefix: params} if isinstance(params, (int, float)) and not isinstance(params, bool) else {}


def _nest(flat: dict, like):
    """``flat`` {path: value} back into the shape of ``like``."""
    if isinstance(like, dict):
        return {k: _nest({p[1:]: v for p, v in flat.items() if p[0] == k}, sub) for k, sub in like.items()
                if any(p[0] == k for p in flat)}
    if isinstance(like, (list, tuple)):
        return [_nest({p[1:]: v for p, v in flat.items() if p[0] == i}, sub) for i, sub in enumerate(like)]
    return flat.get((), None)


def parameter_intervals(e, phys: PhysicsFit, params: dict) -> dict:
    """Percentile interval (``LEVEL``) of each of ``e``'s parameters over the bootstrap
    replicates of ``phys``: see :func:`intervals`."""
    pos = {phys.keys[i]: k for k, i in enumerate(phys.S)}
    return {**intervals(e, [{a: float(b[pos[a]]) for a in e.atoms()} for b in phys.boot], params),
            **e.searched_intervals()}


def intervals(e, replicates: list, params: dict) -> dict:
    """Percentile interval (``LEVEL``) of each of effect ``e``'s parameters over coefficient
    replicates (atom -> value dicts): the parameters' shape with [low, high] in place of each
    number (None where fewer than 10 replicates give a finite value)."""
    reps = [_flatten(e.params(c, {})[0]) for c in replicates]
    lo, hi = 50 * (1 - LEVEL), 50 * (1 + LEVEL)
    out = {}
    for path in _flatten(params):
        v = np.array([r.get(path, np.nan) for r in reps], dtype=float)
        v = v[np.isfinite(v)]
        out[path] = [float(np.percentile(v, lo)), float(np.percentile(v, hi))] if v.size >= 10 else None
    return _nest(out, params)


def _evidence(phys: PhysicsFit, e, err_phys: np.ndarray, alpha: float) -> tuple[dict, int]:
    """Held-out evidence for effect ``e`` in the fitted model: the model without its own atoms
    (load dependence is judged against Coulomb friction, which it extends) against the model
    with them, per fold; and the joint it helps most."""
    index = {a: i for i, a in enumerate(phys.keys)}
    ctx, K, names = phys.ctx, phys.grams.K, phys.ctx.joint_names
    err_wo, err_with, d = own_gain(e, phys.chosen, index, phys.grams, phys.w)
    per_joint = 1 - err_phys.sum(0) / np.maximum(err_wo.sum(0), 1e-300)
    aff = e.affected_joints(ctx)
    jmain = max(aff, key=lambda j: per_joint[j]) if aff else int(np.argmax(per_joint))
    judged = ("on its own joint and on the joint-weighted sum, the smaller p doubled; the weighted total not raised"
              if e.own_joint else "joint-weighted sum")
    ev = {"cv_error_reduction": float(per_joint[jmain]),
          "cv_error_reduction_joint": names[jmain],
          "cv_error_reduction_per_joint": {names[j]: float(per_joint[j]) for j in aff},
          "cv_improvement_in_se": float(d.mean() / (d.std(ddof=1) / np.sqrt(K) + 1e-300)),
          "p_value_without_it": gain_p(e, err_wo, err_with, phys.w),
          "selection_step": phys.chosen.index(e) + 1,
          "criterion": f"{K}-fold time-block CV, one-sided Wilcoxon signed-rank test of the paired held-out "
                       f"gains ({judged}) at family-wise level {alpha:g} (Bonferroni over each step's "
                       "candidates); kept only while its own gain stays significant"}
    ext = [o.name for o in phys.chosen if o is not e and o.index == e.index and o.name in e.requires]
    if ext:
        ev["judged_against"] = ext[0]
    return ev, jmain


def torque_share(phys: PhysicsFit, e, coef: dict, torque_sd: np.ndarray) -> float:
    """How large effect ``e``'s fitted torque is (``coef``: the fit's atom -> coefficient): the
    largest, over the joints it acts on, of its RMS (low-passed columns, every sample) over the
    joint torque's standard deviation ``torque_sd`` (n,) N*m."""
    S = atom_indices([e], {a: i for i, a in enumerate(phys.keys)})
    tq = phys.A[:, :, S] @ np.array([coef.get(phys.keys[i], 0.0) for i in S])
    share = np.sqrt((tq ** 2).mean(0)) / np.maximum(torque_sd, 1e-300)
    joints = e.affected_joints(phys.ctx) or list(range(len(share)))
    return float(share[joints].max())


#: a payload's centre of mass is not determined along a direction where its standard deviation
#: exceeds this, m (a gripper's load placed no better than within a few centimetres)
COM_UNRESOLVED = 0.02


def unresolved_com(phys: PhysicsFit, e, *, given_others: bool = True) -> list[tuple[np.ndarray, float]]:
    """(unit direction (3,) in the link frame, standard deviation m) of each direction along
    which payload ``e``'s centre of mass is not determined (above :data:`COM_UNRESOLVED`).

    Directions: the eigenvectors of the first moments' weighted normal matrix given every other
    chosen atom (``given_others``; else given the payload's mass alone: what the poses of the log
    say about the payload itself, whatever else shares its columns). Along each, the larger of
    two standard deviations: the normal matrix's (residual variance over its eigenvalue, over the
    mass; infinite where the log holds no information, which
    a bootstrap cannot show, every replicate landing on the same arbitrary value) and the block
    bootstrap's. A log that holds one pose determines the mass and the centre across gravity, not
    along it (a vertical force has no moment about a point above or below it)."""
    index = {a: i for i, a in enumerate(phys.keys)}
    pos = [phys.S.index(index[a]) for a in e.atoms()]
    m = float(phys.coef[pos[0]])
    g, S = phys.grams, phys.S
    G, _ = g.normal_equations(S, phys.w)
    rss = g.yte.sum(0) - 2 * g.call[:, S] @ phys.coef + np.einsum("p,jpq,q->j", phys.coef, g.Gall[:, S][:, :, S],
                                                                      phys.coef)
    sigma2 = float(phys.w @ rss / max(g.nte.sum(), 1.0))
    h, o = pos[1:], [k for k in range(len(S)) if k not in pos[1:]] if given_others else [pos[0]]
    H = G[np.ix_(h, h)] - G[np.ix_(h, o)] @ np.linalg.pinv(G[np.ix_(o, o)]) @ G[np.ix_(o, h)]
    lam, V = np.linalg.eigh(H)
    mb = phys.boot[:, pos[0]]
    com_b = phys.boot[mb > 0][:, h] / mb[mb > 0, None]
    C = np.cov(com_b.T) if len(com_b) > 2 else np.zeros((3, 3))
    out = []
    for k in range(3):
        sd = np.sqrt(sigma2 / lam[k]) / m if lam[k] > 1e-12 * max(lam[-1], 1e-300) and m > 0 else np.inf
        sd = max(sd, float(np.sqrt(max(V[:, k] @ C @ V[:, k], 0.0))))
        if sd > COM_UNRESOLVED:
            out.append((V[:, k], float(sd)))
    return out


def _com_statement(finding: dict, unresolved: list) -> dict:
    """``finding`` (a payload's) with the directions of ``unresolved`` its log does not determine
    stated; along one the log holds nothing about (a standard deviation beyond the reach a
    payload's centre is sought in, ``MAX_COM_NORM``) the centre is taken to the point of that line
    nearest the link frame, not left at an arbitrary value."""
    from ..physics.payload import MAX_COM_NORM

    c = np.asarray(finding["params"]["com"], dtype=np.float64)
    for v, sd in unresolved:
        if sd > MAX_COM_NORM:
            c = c - (c @ v) * v
    finding["params"]["com"] = [float(x) for x in c]
    finding["evidence"]["com_unresolved"] = [{"direction": [float(x) for x in v], "std_m": sd} for v, sd in unresolved]
    dirs = "; ".join(f"[{', '.join(f'{x:.2f}' for x in v)}] (+/- {sd:.2g} m)" for v, sd in unresolved)
    moved = any(sd > MAX_COM_NORM for _, sd in unresolved)
    finding["explanation"] += (f" This log does not determine its centre of mass along {dirs} (link frame): the "
                               "poses it holds barely turn that direction across gravity (one pose carries the mass "
                               "and the centre across gravity only)" + ("; the centre given is the point of that "
                               "line nearest the link frame." if moved else "."))
    return finding


def effect_findings(phys: PhysicsFit, *, alpha: float, torque_sd: np.ndarray | None = None,
                    only=None) -> list[dict]:
    """One finding per chosen effect (of ``only``, when given) that no other chosen effect
    contains, with its held-out evidence, standard deviations and block-bootstrap intervals (and,
    given each joint torque's standard deviation ``torque_sd`` (n,), its ``torque_share``)."""
    from .result import effect_finding

    err_phys = phys.grams.cv_errors(phys.S, phys.w)
    coef = phys.coefficients()
    C = phys.cov
    cov = {(phys.keys[a], phys.keys[b]): float(C[ia, ib]) for ia, a in enumerate(phys.S) for ib, b in enumerate(phys.S)}
    findings = []
    for e in phys.chosen:
        if not e.name or any(o is not e and o.index == e.index and e.name in o.supersedes for o in phys.chosen):
            continue
        if only is not None and e not in only:
            continue
        ev, jmain = _evidence(phys, e, err_phys, alpha)
        if torque_sd is not None:
            ev["torque_share"] = torque_share(phys, e, coef, torque_sd)
        params, std = e.params(coef, cov)
        ev = {**ev, "params_std": std, "params_interval": parameter_intervals(e, phys, params),
              "interval_level": LEVEL, "interval_method": f"block bootstrap over the {phys.grams.K} time blocks, "
                                                          f"{len(phys.boot)} replicates, percentile"}
        f = effect_finding(e, params, std, ev, phys.ctx, jmain)
        unresolved = unresolved_com(phys, e) if e.name == "payload" and params["mass"] > 0 else []
        findings.append(_com_statement(f, unresolved) if unresolved else f)
    return findings
