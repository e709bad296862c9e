"""Files shipped inside the package (wheel included): the demo recording."""
from __future__ import annotations

from pathlib import Path

_HERE = Path(__file__).resolve().parent


def demo_files() -> tuple[Path, Path]:
    """The shipped 1-DOF replica of the source experiment: (log, ground-truth labels) Parquet paths.

    Made by ``datasets/make_replica.py`` (MuJoCo, seed 0, 330 samples at 20 Hz); its
    ``datasets/README.md`` describes the recording."""
    return _HERE / "replica" / "replica_log.parquet", _HERE / "replica" / "replica_labels.parquet"
