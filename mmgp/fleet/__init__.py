"""Fleet runs: every log of many robots diagnosed (and optionally trained on) as Ray tasks, one
aggregated table, trend plots and drift (wear) flags. Ray is the optional extra ``mmgp[fleet]``;
it is imported only when a fleet runs on it."""
from .fleet import Fleet, expand_logs  # noqa: F401
