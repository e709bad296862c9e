"""mmgp: multimodal Gaussian-process inverse dynamics from messy robot logs."""
__version__ = "0.1.0"


def load_compensator(path):
    """Load an exported position-only feedforward compensator (numpy only). See mmgp.compensator."""
    from .compensator.field import load_compensator as _load

    return _load(path)
