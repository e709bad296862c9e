"""Rigid-body re-identification: base parameters, physically consistent fits, identifiability.

Joint torques are linear in the bodies' inertial parameters, ``tau = Y(q, dq, ddq) @ pi`` with
``Y`` (T, n, 10 B) Pinocchio's joint torque regressor and ``pi`` the B bodies' parameters in
Pinocchio's order ``[m, m c_x, m c_y, m c_z, Ixx, Ixy, Iyy, Ixz, Iyz, Izz]`` (kg, kg*m, kg*m^2;
inertia about the body's joint frame origin). Not every combination of ``pi`` moves the torques:

* :func:`base_parameters`: the *base parameters* a trajectory determines, by a QR decomposition
  with column pivoting of the stacked regressor (Gautier's numerical method): independent
  columns ``columns`` and the regrouping ``beta = regroup @ pi``, so ``Y @ pi == Y[..., columns]
  @ beta`` for every ``pi``. A linear function ``a @ pi`` of the parameters is identifiable iff
  ``a`` lies in the row space of ``regroup`` (:meth:`BaseParameters.identifiable`).
* :func:`fit_admissible`: least squares under physical constraints: bodies physically consistent,
  magnitudes non-negative, a point mass's first moment within reach, upper bounds.
  :func:`fit_consistent` is its case of the full parameters (plus linear effect coefficients) with
  each body physically consistent: its pseudo-inertia ``[[tr(I)/2 1 - I, h], [h^T, m]]`` positive
  semi-definite (Wensing, Kim and Slotine, RA-L 2018:
  some mass distribution has these parameters), an LMI solved with ``cvxpy``. Directions the data
  do not determine are held at the nominal parameters by a small ridge.
* :func:`identifiability`: condition number of the (column-scaled) base regressor and the
  standard error of each base parameter.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .inertial import point_mass_inertia, unvech

#: names of a body's ten parameters, Pinocchio order
PARAMETER_NAMES = ("m", "mx", "my", "mz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")


@dataclass(frozen=True)
class BaseParameters:
    """The base parameters of a regressor.

    ``columns`` (b,): indices of the independent columns of the full parameter vector (P,);
    ``regroup`` (b, P): ``beta = regroup @ pi``; ``names``: one readable name per base parameter
    (the parameter it is, plus what is regrouped into it); ``body_names``: the B bodies.
    """

    columns: np.ndarray
    regroup: np.ndarray
    names: list
    body_names: list

    @property
    def n_base(self) -> int:
        return len(self.columns)

    def identifiable(self, a: np.ndarray, rtol: float = 1e-6) -> bool:
        """Whether the linear function ``a @ pi`` (a (P,)) is fixed by the base parameters."""
        u = np.linalg.lstsq(self.regroup.T, a, rcond=None)[0]
        return bool(np.linalg.norm(self.regroup.T @ u - a) <= rtol * max(np.linalg.norm(a), 1e-300))

    def body_identifiable(self, k: int) -> dict:
        """Which of body ``k``'s quantities are identifiable: {"mass", "com", "inertia"} -> bool
        (the centre of mass needs m and the three first moments, the inertia all ten)."""
        ok = [self.identifiable(np.eye(self.regroup.shape[1])[10 * k + i]) for i in range(10)]
        return {"mass": ok[0], "com": all(ok[:4]), "inertia": all(ok)}


def _parameter_name(P: int, body_names, i: int) -> str:
    return f"{PARAMETER_NAMES[i % 10]}[{body_names[i // 10]}]" if i < P else f"p{i}"


def base_parameters(Y: np.ndarray, body_names, *, rtol: float = 1e-7, max_rows: int = 4000,
                    seed: int = 0) -> BaseParameters:
    """Base parameters of a regressor ``Y`` (T, n, P), P = 10 B, from a pivoted QR of its stacked
    rows (at most ``max_rows`` samples, evenly spaced) with columns scaled to unit norm. A
    column is dependent when its pivot falls below ``rtol`` times the largest."""
    import scipy.linalg as sl

    T, n, P = Y.shape
    idx = np.unique(np.linspace(0, T - 1, min(T, max_rows)).round().astype(int))
    X = Y[idx].reshape(-1, P)
    scale = np.linalg.norm(X, axis=0)
    live = np.flatnonzero(scale > 1e-12 * max(scale.max(), 1e-300))
    Xs = X[:, live] / scale[live]
    _, R, piv = sl.qr(Xs, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    rank = int((d > rtol * max(d[0], 1e-300)).sum()) if d.size else 0
    ind, dep = live[piv[:rank]], live[piv[rank:]]
    # scaled: X_dep / s_dep = (X_ind / s_ind) R11^-1 R12, so pi_dep regroups into beta_ind
    K = np.linalg.solve(R[:rank, :rank], R[:rank, rank:]) if rank else np.zeros((0, len(dep)))
    K = K * scale[dep][None, :] / scale[ind][:, None]
    order = np.argsort(ind)
    ind, K = ind[order], K[order]
    E = np.zeros((rank, P))
    E[np.arange(rank), ind] = 1.0
    E[:, dep] = K
    names = []
    for i in range(rank):
        extra = [(abs(K[i, d]), dep[d]) for d in range(len(dep)) if abs(K[i, d]) > 1e-9]
        terms = [f"{K[i, list(dep).index(p)]:+.3g}*{_parameter_name(P, body_names, p)}"
                 for _, p in sorted(extra, reverse=True)[:2]]
        more = " ..." if len(extra) > 2 else ""
        names.append(_parameter_name(P, body_names, ind[i]) + "".join(f" {t}" for t in terms) + more)
    return BaseParameters(columns=ind, regroup=E, names=names, body_names=list(body_names))


def identifiability(G: np.ndarray, cov: np.ndarray | None = None) -> dict:
    """Condition number of a Gram matrix ``G`` (b, b) with its columns scaled to unit norm (the
    regressor's condition number squared is that of G: reported as its square root), and the
    standard error of each parameter from ``cov`` (b, b) when given."""
    d = np.sqrt(np.clip(np.diag(G), 1e-300, None))
    ev = np.linalg.eigvalsh(G / np.outer(d, d))
    cond = float(np.sqrt(ev[-1] / max(ev[0], 1e-300))) if ev.size else 1.0
    out = {"condition_number": cond}
    if cov is not None:
        out["std"] = np.sqrt(np.clip(np.diag(cov), 0, None))
    return out


def _pseudo_inertia_expr(p):
    """cvxpy expression of the pseudo-inertia (4, 4) of a body's parameters ``p`` (10,)."""
    import cvxpy as cp

    inertia = cp.bmat([[p[4], p[5], p[7]], [p[5], p[6], p[8]], [p[7], p[8], p[9]]])
    sigma = 0.5 * cp.trace(inertia) * np.eye(3) - inertia
    h = cp.reshape(p[1:4], (3, 1), order="F")
    return cp.bmat([[sigma, h], [h.T, cp.reshape(p[0], (1, 1), order="F")]])


def fit_admissible(G: np.ndarray, c: np.ndarray, *, bodies=(), nonneg=(), cones=(), upper=(),
                   ridge: float = 1e-6) -> tuple[np.ndarray, dict]:
    """Least squares ``min x' G x - 2 c' x`` over ``x`` (N,) under physical constraints.

    ``G`` (N, N), ``c`` (N,): normal equations. ``bodies``: (indices (10,), nominal (10,)) pairs,
    ``nominal + x[indices]`` a rigid body's parameters (Pinocchio order) that must be physically
    consistent (pseudo-inertia PSD); ``nonneg``: indices with ``x >= 0``; ``cones``: (i, indices,
    radius) with ``|x[indices]| <= radius * x[i]`` (a point mass's first moment within reach of its
    frame); ``upper``: (i, bound) with ``x[i] <= bound``. A ridge of ``ridge`` times each body
    column's own Gram diagonal (floored at 1e-9 of the largest) holds what the data do not
    determine at the nominal parameters; other columns get 1e-10 of the largest. Returns ``(x,
    info)`` with the solver status."""
    import cvxpy as cp

    N = len(c)
    d = np.diag(G).copy()
    top = max(d.max(), 1e-300) if N else 1.0
    reg = np.full(N, 1e-10 * top)
    for idx, _ in bodies:
        idx = np.asarray(idx, int)
        reg[idx] = ridge * np.maximum(d[idx], 1e-9 * top)
    scale = np.sqrt(np.clip(d, 1e-300, None) + reg)
    L = np.linalg.cholesky((G + np.diag(reg)) / np.outer(scale, scale) + 1e-12 * np.eye(N))
    y = cp.Variable(N)  # x = y / scale: unit-scaled unknowns keep the conic solver well conditioned
    x = cp.multiply(1.0 / scale, y)
    cons = [_pseudo_inertia_expr(np.asarray(p0, dtype=np.float64) + x[list(idx)]) >> 0 for idx, p0 in bodies]
    if len(nonneg):
        cons.append(x[list(nonneg)] >= 0)
    cons += [cp.norm(x[list(h)]) <= r * x[i] for i, h, r in cones]
    cons += [x[i] <= b for i, b in upper]
    prob = cp.Problem(cp.Minimize(cp.sum_squares(L.T @ y - np.linalg.solve(L, c / scale))), cons)
    try:
        prob.solve(solver=cp.CLARABEL)
    except cp.SolverError:
        prob.solve(solver=cp.SCS, eps=1e-9, max_iters=20000)
    if y.value is None:
        raise RuntimeError(f"physically constrained fit failed ({prob.status})")
    return np.asarray(y.value) / scale, {"status": prob.status}


def fit_consistent(G: np.ndarray, c: np.ndarray, pi0: np.ndarray, *, nonneg: np.ndarray | None = None,
                   ridge: float = 1e-6) -> tuple[np.ndarray, dict]:
    """Least squares ``min x' G x - 2 c' x`` over ``x = [dpi (P,), theta (p,)]`` with every body
    of ``pi0 + dpi`` physically consistent (pseudo-inertia PSD) and ``theta[nonneg] >= 0``
    (:func:`fit_admissible`).

    ``G`` (P + p, P + p), ``c`` (P + p,) the normal equations of the regressor (first P columns,
    P = 10 B) and of the effect columns; ``pi0`` (P,) nominal parameters; ``ridge`` holds what the
    data do not determine at the nominal parameters. Returns ``(x, info)`` with the solver status.
    """
    P = len(pi0)
    nonneg = np.zeros(len(c) - P, bool) if nonneg is None else np.asarray(nonneg, bool)
    bodies = [(np.arange(10 * k, 10 * k + 10), pi0[10 * k:10 * k + 10]) for k in range(P // 10)]
    return fit_admissible(G, c, bodies=bodies, nonneg=P + np.flatnonzero(nonneg), ridge=ridge)


def body_quantities(pi: np.ndarray) -> dict:
    """Mass (kg), centre of mass (3,) m and inertia about the centre of mass (3, 3) kg*m^2 of a
    body's parameters (10,) (com and inertia NaN for a non-positive mass)."""
    m, h = float(pi[0]), np.asarray(pi[1:4], dtype=np.float64)
    if not m > 0:
        return {"mass": m, "com": np.full(3, np.nan), "inertia": np.full((3, 3), np.nan)}
    com = h / m
    return {"mass": m, "com": com, "inertia": unvech(pi[4:10]) - m * unvech(point_mass_inertia(com))}


def _inertia6(I: np.ndarray) -> list:
    """[Ixx, Iyy, Izz, Ixy, Ixz, Iyz] of a (3, 3) inertia (CONTRACT order)."""
    return [float(I[0, 0]), float(I[1, 1]), float(I[2, 2]), float(I[0, 1]), float(I[0, 2]), float(I[1, 2])]


def body_parameters(pi0: np.ndarray, pi: np.ndarray, base: BaseParameters, rtol: float = 1e-9) -> dict:
    """The bodies of ``pi`` (P,) that differ from ``pi0`` (P,), whole: {body: {"mass": kg, "com":
    [3] m, "inertia": [Ixx, Iyy, Izz, Ixy, Ixz, Iyz] kg*m^2 about the com}} (link frame). A
    physically consistent fit's bodies are one mass distribution with the identified base
    parameters; a model built from them predicts what the base parameters predict, where
    :func:`body_deltas` may name nothing (no single body's quantity identifiable). A body no base
    parameter involves (its columns left out, e.g. a payload link's) is not the fit's to change."""
    out = {}
    scale = max(float(np.abs(pi0).max()), 1e-300)
    for k, name in enumerate(base.body_names):
        a, b = pi0[10 * k:10 * k + 10], pi[10 * k:10 * k + 10]
        if not np.abs(base.regroup[:, 10 * k:10 * k + 10]).any() or np.abs(b - a).max() <= rtol * scale:
            continue
        q = body_quantities(b)
        out[name] = {"mass": q["mass"], "com": [float(x) for x in q["com"]], "inertia": _inertia6(q["inertia"])}
    return out


def body_deltas(pi0: np.ndarray, pi: np.ndarray, base: BaseParameters) -> dict:
    """Per body, identified minus nominal for what the base parameters determine (CONTRACT
    ``inertial_parameters`` ``delta``): {body: {"mass": kg, "com": [3] m, "inertia": [Ixx, Iyy,
    Izz, Ixy, Ixz, Iyz] kg*m^2 about the com}}, each only where identifiable; bodies with
    nothing identifiable are left out."""
    out = {}
    for k, name in enumerate(base.body_names):
        ok = base.body_identifiable(k)
        a, b = body_quantities(pi0[10 * k:10 * k + 10]), body_quantities(pi[10 * k:10 * k + 10])
        d = {}
        if ok["mass"]:
            d["mass"] = b["mass"] - a["mass"]
        if ok["com"]:
            d["com"] = [float(x) for x in b["com"] - a["com"]]
        if ok["inertia"]:
            d["inertia"] = _inertia6(b["inertia"] - a["inertia"])
        if d:
            out[name] = d
    return out
