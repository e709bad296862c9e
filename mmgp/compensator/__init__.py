"""Passive position-only feedforward compensator: ``tau_ff(q) = grad V(q)`` with a storage
function bounded below.

``field`` (the numpy-only evaluator :class:`Compensator`, the file format, :func:`load_compensator`),
``fit`` (:func:`compensator_from_model`), ``passivity`` (:func:`check_passivity`, storage bounds),
``csource`` (C export). Importing this package or ``mmgp.compensator.field`` pulls in neither torch
nor scipy; ``compensator_from_model`` (torch) is imported on first use.
"""
from __future__ import annotations

from .field import Compensator, load_compensator
from .passivity import check_passivity

__all__ = ["Compensator", "load_compensator", "check_passivity", "compensator_from_model"]


def __getattr__(name):
    if name == "compensator_from_model":
        from .fit import compensator_from_model

        return compensator_from_model
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
