"""The compactly supported potential kernel of the compensator: Wendland's functions.

A potential ``V ~ GP(0, k)`` with ``k(x, x') = s2 phi(|u|)``, ``u = (x - x')/l`` (per-joint support
radii ``l``), observed through its gradient, needs only two radial functions (for any kernel of
this form; see :mod:`mmgp.gp.gradient_field`)::

    cov(dV/dx_i, dV/dx'_j) = s2 (A(r) delta_ij - B(r) u_i u_j) / (l_i l_j),
    A(r) = -phi'(r)/r,   B(r) = (phi''(r) - phi'(r)/r) / r^2,

and the posterior mean is ``V(q) = s2 sum_a A(r_a) (u_a . gamma_a)``, ``tau_i = dV/dq_i =
s2/l_i sum_a (A(r_a) gamma_ai - B(r_a) u_ai (u_a . gamma_a))`` with ``gamma_a = alpha_a / l``.
(The Gaussian ``phi = exp(-r^2/2)`` has ``A = B = phi``.)

Wendland's functions make both exactly zero for ``r >= 1``: with ``psi_{l,0}(r) = (1 - r)_+^l`` and
``psi_{l,j+1}(r) = int_r^1 t psi_{l,j}(t) dt`` one has ``psi_{l,j}' = -r psi_{l,j-1}``, so for
``phi = psi_{l,k} / psi_{l,k}(0)``: ``A = psi_{l,k-1} / psi_{l,k}(0)`` and ``B = psi_{l,k-2} / psi_{l,k}(0)``,
piecewise polynomials. ``phi`` is positive definite on R^d for ``l >= floor(d/2) + k + 1``
(Wendland 1995) and is C^{2k} as a function of x; we take ``l = floor(d/2) + k + 1`` and, by
default, ``k = 3`` (V is C^6-smooth as a radial function; tau = grad V has two derivatives to spare,
so the loop integrals of :func:`mmgp.compensator.passivity.check_passivity` converge fast).

Closed forms (checked against the recursive integral in the tests), ``t = (1 - r)_+``::

    psi_{l,0} = t^l
    psi_{l,1} = t^(l+1) ((l+1) r + 1) / ((l+1)(l+2))
    psi_{l,2} = t^(l+2) ((l^2+4l+3) r^2 + (3l+6) r + 3) / ((l+1)(l+2)(l+3)(l+4))
    psi_{l,3} = t^(l+3) ((l^3+9l^2+23l+15) r^3 + (6l^2+36l+45) r^2 + (15l+45) r + 15) / ((l+1)...(l+6))

The profile's functions use only ``+ - * **`` and a comparison, so they evaluate numpy arrays and
torch tensors alike (the GP fit differentiates them with autograd; the numpy evaluator and the
C source use the same coefficient arrays).
"""
from __future__ import annotations

import math

import numpy as np

SMOOTHNESS = (2, 3)
#: the Wendland smoothness k a compensator's kernel has unless told
DEFAULT_SMOOTHNESS = 3


def _psi_polynomial(l: int, j: int) -> tuple[int, np.ndarray]:
    """(exponent of (1 - r)_+, ascending coefficients incl. the normaliser) of psi_{l,j}."""
    if j == 0:
        p, c = [1.0], 1.0
    elif j == 1:
        p, c = [1.0, l + 1.0], (l + 1.0) * (l + 2)
    elif j == 2:
        p, c = [3.0, 3.0 * l + 6, l * l + 4.0 * l + 3], math.prod(l + i for i in range(1, 5))
    elif j == 3:
        p = [15.0, 15.0 * l + 45, 6.0 * l * l + 36 * l + 45, l ** 3 + 9.0 * l * l + 23 * l + 15]
        c = math.prod(l + i for i in range(1, 7))
    else:
        raise ValueError(f"psi_(l,{j}) is not tabulated")
    return l + j, np.asarray(p, dtype=np.float64) / c


def _evaluate(exponent: int, coef: np.ndarray, r):
    t = (1.0 - r) * (r < 1.0)
    p = float(coef[-1])
    for c in coef[-2::-1]:
        p = p * r + float(c)
    return t ** exponent * p


class WendlandProfile:
    """Radial functions ``A(r)``, ``B(r)`` of the Wendland potential kernel for ``n_dims`` inputs.

    ``smoothness`` k in (2, 3); ``degree`` l = floor(n_dims / 2) + k + 1. ``A(r)``/``B(r)``: r >= 0
    (numpy array or torch tensor) -> same type, zero for r >= 1. ``phi(r)`` is the normalised
    kernel profile (phi(0) = 1), ``a0 = A(0)``. ``terms("A")``/``terms("B")``: (exponent,
    ascending coefficients) with ``A(r) = (1 - r)_+^exponent * sum_i coef_i r^i``.
    """

    support_radius = 1.0

    def __init__(self, n_dims: int, smoothness: int = DEFAULT_SMOOTHNESS):
        if smoothness not in SMOOTHNESS:
            raise ValueError(f"Wendland smoothness must be one of {SMOOTHNESS}, got {smoothness}")
        if n_dims < 1:
            raise ValueError("n_dims must be >= 1")
        self.n_dims, self.smoothness = int(n_dims), int(smoothness)
        self.degree = self.n_dims // 2 + self.smoothness + 1
        e, c = _psi_polynomial(self.degree, self.smoothness)
        self._c0 = float(c[0])  # psi_{l,k}(0)
        self._phi = (e, c / self._c0)
        self._terms = {}
        for name, j in (("A", self.smoothness - 1), ("B", self.smoothness - 2)):
            e, c = _psi_polynomial(self.degree, j)
            self._terms[name] = (e, c / self._c0)
        self.a0 = float(self._terms["A"][1][0])

    def terms(self, which: str) -> tuple[int, np.ndarray]:
        e, c = self._terms[which]
        return e, c.copy()

    def phi(self, r):
        return _evaluate(*self._phi, r)

    def A(self, r):
        return _evaluate(*self._terms["A"], r)

    def B(self, r):
        return _evaluate(*self._terms["B"], r)

    def as_dict(self) -> dict:
        return {"name": "wendland", "smoothness": self.smoothness, "degree": self.degree,
                "support_radius": self.support_radius}

    def __repr__(self):
        return f"WendlandProfile(n_dims={self.n_dims}, smoothness={self.smoothness}, degree={self.degree})"
