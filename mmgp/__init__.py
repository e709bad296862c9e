"""mmgp: multimodal Gaussian-process inverse dynamics from messy robot logs.

Public API (imported on first use, so ``import mmgp`` loads neither torch nor pinocchio):

- :class:`MultimodalGP`: learn modes, disturbance labels and per-mode GPs from logs; predict,
  save / load, export the passive feedforward (``to_compensator``).
- :class:`Diagnoser`: name the physics a nominal robot model misses, from a log.
- :func:`load_compensator`: an exported feedforward (numpy only).
- :func:`read_log`, :class:`RobotLog`: a checked log (docs/contract.md).
- :class:`RobotModel`, :func:`load_robot`: Pinocchio rigid-body models.
- :class:`InputError`: the one error for bad input.
- :func:`demo_files`: the shipped demo recording and its ground-truth labels (Parquet paths).
"""
from __future__ import annotations

import importlib

from ._version import __version__

_LAZY = {
    "MultimodalGP": ".estimator",
    "Diagnoser": ".diagnosis",
    "load_compensator": ".compensator.field",
    "read_log": ".data.logs",
    "RobotLog": ".data.logs",
    "RobotModel": ".physics.robot",
    "load_robot": ".physics.robot",
    "InputError": ".errors",
    "demo_files": ".resources",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'mmgp' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
