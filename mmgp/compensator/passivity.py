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
    """Rigorous (lower, upper) bounds of V on all of R^n, and how they were obtained.

    Triangle bound (always valid, usually very loose because GP weights alternate in sign):
    curl-free ``B_tri = s2 e^{-1/2} sum_a |gamma_a|``; erf-1dof ``B_tri = sum_a |A_a|``.
    Tighter bounds: :func:`_curl_free_rkhs_bound` and :func:`_erf_grid_bound`. Each bound is
    widened by a rounding allowance (1e-12 of the sum of absolute terms).
    """
    if comp.kind == "curl-free-rbf":
        return _curl_free_rkhs_bound(comp)
    return _erf_grid_bound(comp)


def _curl_free_rkhs_bound(comp) -> tuple[float, float, dict]:
    """V = sum_ai alpha_ai d k(., z_a)/dz_i lies in the RKHS of k with ``|V|_H^2 = alpha^T K_dd alpha``,
    and ``|V(q)| = |<V, k(., q)>| <= |V|_H sqrt(s2)``.

    The quadratic form needs only (N, N) matrices: with ``P = zs gamma^T``, ``d_a = zs_a.gamma_a``,
    ``alpha^T K alpha = sum_ab k_ab (gamma_a.gamma_b - (d_a - P_ba)(P_ab - d_b))``.
    """
    N = comp.support.shape[0]
    G, zs, s2 = comp._gamma, comp._zs, comp.signal_var
    tri = float(s2 * _EXP_M_HALF * np.sum(np.sqrt(np.sum(G * G, axis=1))))
    if N * N * comp.n_joints <= 2e7:
        D = zs[:, None, :] - zs[None, :, :]
        k = s2 * np.exp(-0.5 * np.sum(D * D, axis=2))
    else:
        sq = np.sum(zs ** 2, axis=1)
        k = s2 * np.exp(-0.5 * np.maximum(sq[:, None] + sq[None] - 2 * zs @ zs.T, 0))
    P = zs @ G.T
    d = np.sum(zs * G, axis=1)
    terms = k * (G @ G.T - (d[:, None] - P.T) * (P - d[None, :]))
    qf = float(np.sum(terms)) + 1e-12 * float(np.sum(np.abs(terms)))
    rkhs = math.sqrt(s2 * max(qf, 0.0))
    B = min(tri, rkhs) * (1 + 1e-12) + 1e-12 * tri
    return -B, B, {"method": "rkhs" if rkhs < tri else "triangle", "triangle_bound": tri, "rkhs_bound": rkhs}


def _erf_grid_bound(comp) -> tuple[float, float, dict]:
    """|tau| <= T = sqrt(s2 w^T K w) (the RKHS argument for tau), so on a grid of spacing h covering
    the support +- 12 l, ``V >= min_grid V - T h / 2`` between nodes; beyond the grid
    ``|V(q) - V(end)| <= sum_a |A_a| erfc(12/sqrt 2)``, negligible."""
    tri = float(np.sum(np.abs(comp._erf_amp)))
    l = comp.lengthscales[0]
    z = comp.support[:, 0]
    w = comp.weights[:, 0]
    U = (z[:, None] - z[None, :]) / l
    wKw = float(w @ (comp.signal_var * np.exp(-0.5 * U * U)) @ w)
    T = math.sqrt(comp.signal_var * max(wKw, 0.0))
    span = float(z.max() - z.min()) + 24 * l
    h = max(l / 200.0, span / 20000.0)  # cap the grid; a coarser step only widens the slack
    grid = np.arange(z.min() - 12 * l, z.max() + 12 * l + h, h)
    V = comp.potential(grid[:, None])
    tail = tri * math.erfc(12 / math.sqrt(2))
    slack = T * h / 2 + tail + 1e-12 * tri
    lo, hi = float(V.min()) - slack, float(V.max()) + slack
    lo, hi = max(lo, -tri), min(hi, tri)
    return lo, hi, {"method": "grid+rkhs-lipschitz", "triangle_bound": tri, "torque_bound": T, "grid_step": float(h)}


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

    ``bounds``: (2, n) box; default ``comp.bounds`` if present, else [-pi, pi]^n.
    Returns a dict of worst figures and ``passed`` (all three).
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
    res["passed"] = bool(res["grad_pass"] and res["loop_pass"] and res["storage_bounded_pass"])
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
