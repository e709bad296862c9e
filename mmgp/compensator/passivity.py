"""Storage bounds of an exported compensator and the numerical passivity check (numpy only).

``potential_bounds`` gives rigorous lower and upper bounds of the potential V on all of R^n (the
storage function is ``S = V - lower >= 0``); ``storage_sampled_min`` the smallest storage found
over the workspace box (scipy, imported when called); ``check_passivity`` checks numerically that a
field is the gradient of a storage bounded below.
"""
from __future__ import annotations

import math

import numpy as np

_EXP_M_HALF = math.exp(-0.5)


def potential_bounds(comp) -> tuple[float, float, dict]:
    """Rigorous (lower, upper) bounds of the deviation potential V_dev on all of R^n, and how they
    were obtained; ``info["torque_bound"]`` (n,) bounds ``|dV_dev/dq_i|`` everywhere.

    Triangle bound (always valid, usually very loose because GP weights alternate in sign):
    curl-free ``B_tri = s2 max_r(r A(r)) sum_a |gamma_a|``; erf-1dof ``B_tri = sum_a |A_a|``.
    Tighter bounds: :func:`_curl_free_rkhs_bound` and :func:`_erf_grid_bound`. Each bound is
    widened by a rounding allowance (1e-12 of the sum of absolute terms). The prior's bounds are
    added by the caller.
    """
    if comp.kind == "erf-1dof":
        return _erf_grid_bound(comp)
    lo, hi, info = _curl_free_rkhs_bound(comp)
    if comp.n_joints == 1:  # one joint: a grid with the RKHS torque bound as Lipschitz constant is tight
        compact = math.isfinite(comp.region_radius)
        reach = comp.lengthscales[0] * (comp.region_radius if compact else 12.0)
        # beyond 12 l a Gaussian term is below s2 |gamma| 12 e^-72 < 1e-30 of the triangle bound
        g_lo, g_hi, h = _grid_bound(comp, info["torque_bound"][0], reach, 0.0 if compact else 1e-30 * info["triangle_bound"],
                                    info["triangle_bound"])
        lo, hi = max(lo, g_lo), min(hi, g_hi)
        info.update(method="grid+rkhs-lipschitz", grid_step=h)
    return lo, hi, info


def _max_r_a(profile) -> float:
    """max_r r A(r): e^{-1/2} for the RBF; for a Wendland profile a grid of 10^5 points on [0, 1]
    widened by 1e-3 (r A(r) is a polynomial of bounded slope there)."""
    if profile is None:
        return _EXP_M_HALF
    r = np.linspace(0.0, 1.0, 100_001)
    return float(np.max(r * profile.A(r))) * 1.001


def _curl_free_rkhs_bound(comp) -> tuple[float, float, dict]:
    """V = sum_ai alpha_ai d k(., z_a)/dz_i lies in the RKHS of k with ``|V|_H^2 = alpha^T K_dd alpha``,
    so ``|V(q)| = |<V, k(., q)>| <= |V|_H sqrt(s2)`` and ``|dV/dq_i| <= |V|_H sqrt(s2 A(0)) / l_i``.

    The quadratic form needs only (N, N) matrices: with ``P = zs gamma^T``, ``d_a = zs_a.gamma_a``,
    ``alpha^T K alpha = sum_ab s2 (A_ab gamma_a.gamma_b - B_ab (d_a - P_ba)(P_ab - d_b))``.
    """
    N = comp.support.shape[0]
    G, zs, s2 = comp._gamma, comp._zs, comp.signal_var
    tri = float(s2 * _max_r_a(comp.profile) * np.sum(np.sqrt(np.sum(G * G, axis=1))))
    if N * N * comp.n_joints <= 2e7:
        D = zs[:, None, :] - zs[None, :, :]
        r2 = np.sum(D * D, axis=2)
    else:
        sq = np.sum(zs ** 2, axis=1)
        r2 = np.maximum(sq[:, None] + sq[None] - 2 * zs @ zs.T, 0)
    a, b = comp._radial(r2)
    P = zs @ G.T
    d = np.sum(zs * G, axis=1)
    terms = a * (G @ G.T) - b * ((d[:, None] - P.T) * (P - d[None, :]))
    qf = max(float(np.sum(terms)) + 1e-12 * float(np.sum(np.abs(terms))), 0.0)
    rkhs = math.sqrt(s2 * qf)
    B = min(tri, rkhs) * (1 + 1e-12) + 1e-12 * tri
    a0 = 1.0 if comp.profile is None else comp.profile.a0
    torque = (math.sqrt(qf * s2 * a0) * (1 + 1e-12)) * comp._inv_l
    return -B, B, {"method": "rkhs" if rkhs < tri else "triangle", "triangle_bound": tri, "rkhs_bound": rkhs,
                   "rkhs_norm": math.sqrt(qf), "torque_bound": torque.tolist()}


def _erf_grid_bound(comp) -> tuple[float, float, dict]:
    """erf-1dof: ``|tau| <= T = sqrt(s2 w^T K w)`` (the RKHS argument for tau), then
    :func:`_grid_bound` over the support +- 12 l; beyond it ``|V(q) - V(end)| <= sum_a |A_a|
    erfc(12/sqrt 2)``, negligible."""
    tri = float(np.sum(np.abs(comp._erf_amp)))
    l = comp.lengthscales[0]
    w = comp.weights[:, 0]
    U = (comp.support[:, 0][:, None] - comp.support[:, 0][None, :]) / l
    T = math.sqrt(comp.signal_var * max(float(w @ (comp.signal_var * np.exp(-0.5 * U * U)) @ w), 0.0))
    lo, hi, h = _grid_bound(comp, T, 12 * l, tri * math.erfc(12 / math.sqrt(2)), tri)
    return lo, hi, {"method": "grid+rkhs-lipschitz", "triangle_bound": tri, "torque_bound": [T], "grid_step": h}


def _grid_bound(comp, T: float, reach: float, tail: float, tri: float) -> tuple[float, float, float]:
    """One joint: V_dev on a grid of spacing h covering the support +- ``reach``, widened by the
    Lipschitz slack ``T h / 2`` (``|dV/dq| <= T``), the ``tail`` beyond the grid and rounding.
    Returns (lower, upper, h)."""
    z = comp.support[:, 0]
    h = max(reach / 2400.0, (float(z.max() - z.min()) + 2 * reach) / 20000.0)  # a coarser step only widens the slack
    grid = np.arange(z.min() - reach, z.max() + reach + h, h)
    _, V, _ = comp._eval(grid[:, None], False, True, with_prior=False)
    slack = T * h / 2 + tail + 1e-12 * tri
    return max(float(V.min()) - slack, -tri), min(float(V.max()) + slack, tri), float(h)


def storage_sampled_min(comp, seed: int = 0, n_samples: int = 20000) -> tuple[float, np.ndarray]:
    """Smallest storage found over the workspace box: random points, support points, then a
    bounded L-BFGS-B polish (gradient = torque) from the five best. Returns (min J, argmin (n,))."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    lo, hi = comp.bounds
    cand = np.concatenate([lo + rng.random((n_samples, comp.n_joints)) * (hi - lo), comp.support])
    S = comp.storage(cand)
    best = np.argsort(S)[:5]
    s_min, q_min = float(S[best[0]]), cand[best[0]]
    for i in best:
        r = minimize(lambda x: (comp.storage(x), comp.torque(x)), cand[i], jac=True,
                     method="L-BFGS-B", bounds=list(zip(lo, hi)), options={"maxiter": 200})
        if r.fun < s_min:
            s_min, q_min = float(r.fun), r.x
    return s_min, q_min


def deviation_sampled_max(comp, seed: int = 0, n_samples: int = 20000, n_polish: int = 2) -> np.ndarray:
    """Largest ``|tau_ff - tau_prior|`` per joint (n,) N*m found where the deviation can be non-zero.

    Candidates: the support points and ``n_samples`` points drawn uniformly in the balls of radius
    ``region_radius`` (3 for a Gaussian kernel) around random support points, in the kernel's
    metric; then a bounded L-BFGS-B polish (finite-difference gradient) of each joint's
    ``|tau_dev,i|`` from its ``n_polish`` best candidates. A search, not a proof: the rigorous
    bound is ``comp.deviation_torque_bound``."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    n = comp.n_joints
    radius = comp.region_radius if math.isfinite(comp.region_radius) else 3.0
    centre = comp.support[rng.integers(comp.support.shape[0], size=n_samples)]
    u = rng.normal(size=(n_samples, n))
    u *= (radius * rng.random(n_samples) ** (1.0 / n) / np.linalg.norm(u, axis=1))[:, None]
    cand = np.concatenate([comp.support, centre + u * comp.lengthscales])
    dev = np.abs(comp.deviation_torque(cand))
    best = dev.max(axis=0)
    for i in range(n):
        for k in np.argsort(dev[:, i])[-n_polish:]:
            r = minimize(lambda x: -abs(float(comp.deviation_torque(x)[i])), cand[k], method="L-BFGS-B",
                         options={"maxiter": 50})
            best[i] = max(best[i], -float(r.fun))
    return best


def check_passivity(comp, n_configs: int = 200, n_loops: int = 50, bounds=None, seed: int = 0, *,
                    n_quad: int = 512, grad_rtol: float = 1e-6, loop_rtol: float = 1e-9,
                    n_storage_samples: int = 20000) -> dict:
    """Numerically check that ``comp.torque`` is the gradient of a storage bounded below.

    Works on any object with ``torque(q)`` ((T, n) -> (T, n)) and ``storage(q)`` ((T, n) -> (T,));
    for a non-conservative field ``storage`` may be any candidate: the loop test fails regardless.

    1. Gradient: at ``n_configs`` uniform configurations in ``bounds``, 4th-order central
       differences of ``storage`` (step ``1e-3`` of the box width) against ``torque``; figure:
       max |fd - tau| / torque scale, pass below ``grad_rtol``.
    2. Loops: ``n_loops`` random smooth closed curves ``q(s) = c + sum_k a_k cos 2 pi k s + b_k sin 2 pi k s``
       (k = 1..3) in the box; work ``W = int_0^1 tau(q(s)) . q'(s) ds`` by the trapezoid rule on
       ``n_quad`` nodes, which converges geometrically for periodic analytic integrands.
       Figure: max |W| / (torque scale * loop length); pass below ``loop_rtol``.
    3. Lower bound: ``storage`` at ``n_storage_samples`` points in the box and in a box 5x wider;
       pass if the minimum is finite and not below ``comp.storage_lower_bound`` (when present).
    4. Prior: when ``comp`` has a rigid-body ``prior``, it must be physically consistent
       (``prior_problems`` lists what is not; a :class:`~mmgp.compensator.Compensator` cannot be
       built with such a prior, so this catches objects assembled otherwise).

    ``bounds``: (2, n) box; default ``comp.bounds`` if present, else [-pi, pi]^n.
    Returns a dict of worst figures and ``passed`` (all four).
    """
    rng = np.random.default_rng(seed)
    if bounds is None:
        bounds = getattr(comp, "bounds", None)
    if bounds is None:
        n = _infer_n(comp)
        bounds = np.stack([-np.pi * np.ones(n), np.pi * np.ones(n)])
    bounds = np.asarray(bounds, dtype=np.float64)
    lo, hi = bounds[0], bounds[1]
    width = np.where(hi > lo, hi - lo, 1.0)
    tau_scale, grad_err = _gradient_error(comp, lo, width, n_configs, rng)
    worst_rel, worst_abs = _loop_work(comp, lo, width, n_loops, n_quad, tau_scale, rng)
    s_min, lb, bounded = _storage_minimum(comp, lo, hi, width, n_storage_samples, rng)
    res = {
        "n_configs": n_configs, "n_loops": n_loops,
        "torque_scale": tau_scale,
        "grad_max_rel_err": grad_err, "grad_pass": bool(grad_err <= grad_rtol),
        "loop_max_rel_work": worst_rel, "loop_max_abs_work": worst_abs,
        "loop_pass": bool(worst_rel <= loop_rtol),
        "storage_min_sampled": s_min,
        "storage_lower_bound": None if lb is None else float(lb),
        "storage_bounded_pass": bounded,
    }
    prior = getattr(comp, "prior", None)
    res["prior_problems"] = [] if prior is None else list(prior.consistency_problems())
    res["prior_consistent_pass"] = not res["prior_problems"]
    res["passed"] = bool(res["grad_pass"] and res["loop_pass"] and res["storage_bounded_pass"]
                         and res["prior_consistent_pass"])
    return res


def _gradient_error(comp, lo, width, n_configs, rng) -> tuple[float, float]:
    """(torque scale, max |finite-difference gradient of storage - torque| / torque scale)."""
    n = lo.shape[0]
    Q = lo + rng.random((n_configs, n)) * width
    tau = np.asarray(comp.torque(Q), dtype=np.float64).reshape(n_configs, n)
    h = 1e-3 * width
    fd = np.empty_like(tau)
    for i in range(n):
        e = np.zeros(n)
        e[i] = h[i]
        s = [np.asarray(comp.storage(Q + c * e), dtype=np.float64) for c in (-2, -1, 1, 2)]
        fd[:, i] = (s[0] - 8 * s[1] + 8 * s[2] - s[3]) / (12 * h[i])
    tau_scale = float(max(np.max(np.abs(tau)), 1e-300))
    return tau_scale, float(np.max(np.abs(fd - tau)) / tau_scale)


def _loop_work(comp, lo, width, n_loops, n_quad, tau_scale, rng, n_harmonics: int = 3) -> tuple[float, float]:
    """Worst relative and absolute work of the torque around random smooth closed loops in the box."""
    n = lo.shape[0]
    s = np.arange(n_quad) / n_quad
    worst_rel, worst_abs = 0.0, 0.0
    K = n_harmonics
    for _ in range(n_loops):
        c = lo + (0.3 + 0.4 * rng.random(n)) * width
        amp = rng.normal(size=(2, K, n)) / (np.arange(1, K + 1)[None, :, None] ** 1.5)
        # keep the curve inside the box: scale so the largest excursion is 0.25 of the width
        scale = 0.25 * width / np.maximum(np.sum(np.abs(amp), axis=(0, 1)), 1e-12)
        a, b = amp[0] * scale, amp[1] * scale
        w = 2 * np.pi * np.arange(1, K + 1)
        cs, sn = np.cos(np.outer(s, w)), np.sin(np.outer(s, w))  # (M, K)
        qs = c + cs @ a + sn @ b
        dqs = (-sn * w) @ a + (cs * w) @ b
        tq = np.asarray(comp.torque(qs), dtype=np.float64).reshape(n_quad, n)
        W = float(np.mean(np.sum(tq * dqs, axis=1)))
        length = float(np.mean(np.linalg.norm(dqs, axis=1)))
        scale_t = max(float(np.max(np.abs(tq))), tau_scale)
        worst_abs = max(worst_abs, abs(W))
        worst_rel = max(worst_rel, abs(W) / (scale_t * length))
    return worst_rel, worst_abs


def _storage_minimum(comp, lo, hi, width, n_samples, rng):
    """(sampled minimum of storage in the box and a 5x wider one, the claimed lower bound or None,
    whether the minimum is finite and not below it)."""
    n = lo.shape[0]
    Qs = lo + rng.random((n_samples, n)) * width
    Qw = (lo + hi) / 2 + (rng.random((n_samples // 4, n)) - 0.5) * 5 * width
    S = np.concatenate([np.asarray(comp.storage(Qs), dtype=np.float64).ravel(),
                        np.asarray(comp.storage(Qw), dtype=np.float64).ravel()])
    s_min = float(np.min(S))
    lb = getattr(comp, "storage_lower_bound", None)
    bounded = bool(np.isfinite(s_min) and (lb is None or s_min >= lb - 1e-12 * max(1.0, abs(s_min))))
    return s_min, lb, bounded


def _infer_n(comp) -> int:
    for attr in ("n_joints", "n"):
        if hasattr(comp, attr):
            return int(getattr(comp, attr))
    raise ValueError("check_passivity: pass bounds= for an object without bounds/n_joints")
