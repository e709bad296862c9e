"""Logs in, checked arrays out: reading and checking logs and labels, differentiation, time-block
folds, and writing outputs completely or not at all."""
