"""Sim-vs-real diagnosis: which physics a nominal rigid-body model misses (``Diagnoser``)."""
from .pipeline import Diagnoser
from .result import DiagnosisResult
from .selection import ForwardCVSelector

__all__ = ["Diagnoser", "DiagnosisResult", "ForwardCVSelector"]
