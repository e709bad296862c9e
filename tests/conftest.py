"""Shared test settings.

The test machine is shared by several people: multi-threaded BLAS on the small matrices these
tests use spends its time spin-waiting for cores other processes hold, so one thread is both
faster and far more predictable.
"""
import torch

torch.set_num_threads(1)
