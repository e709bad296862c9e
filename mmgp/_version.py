"""The package version, at the lowest layer so every module may read it."""
__version__ = "0.1.0"
