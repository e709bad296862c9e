"""The RBF GPs' settings, declared once (torch-free: the estimator reads its defaults from here).

:class:`HyperProcedure` is what :func:`mmgp.gp.hyper.fit_hyper_subsets` does with a GP's data:
subset sizes, L-BFGS iterations, the objective ("loo" or "marginal"; leave-block-out of
``block_s`` seconds when times are given), ARD, the noise floor, the subsets' seed, independent
outputs, refinement rounds and shared starts, and whether it runs at all (``optimise``; False:
the GP keeps the hyperparameters it is given). Its defaults are those of
:class:`mmgp.gp.exact.ExactGP`, :class:`mmgp.gp.sparse.SparseGP` and the GP settings
:class:`mmgp.MultimodalGP` exposes (``ard``, ``objective``), which are written ``GP_DEFAULTS.<name>``.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class HyperProcedure:
    """The settings of the hyperparameter procedure (module docstring); the GPs' of the same names."""

    max_fit_points: int = 1000
    coarse_fit_points: int = 300
    max_iter: int = 60
    objective: str = "loo"
    ard: bool = True
    noise_floor: float = 1e-6
    seed: int = 0
    independent_outputs: bool = False
    refine_rounds: int = 1
    shared_starts: bool = False
    block_s: float = 0.0
    optimise: bool = True


#: the defaults every RBF GP setting is written as (``GP_DEFAULTS.<name>``)
GP_DEFAULTS = HyperProcedure()
