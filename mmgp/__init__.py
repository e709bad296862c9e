"""mmgp: multimodal Gaussian-process inverse dynamics from messy robot logs."""
from ._version import __version__  # noqa: F401


def load_compensator(path):
    """Load an exported position-only feedforward compensator (numpy only). See mmgp.compensator."""
    from .compensator.field import load_compensator as _load

    return _load(path)
