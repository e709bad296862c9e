"""Files shipped inside the package (wheel included): the demo recording and the settings files.

The settings files live in ``mmgp/resources/configs/``; the repository's top-level ``configs``
is a link to that folder, so ``--config configs/default.yaml`` works in a checkout and
``mmgp config show default`` prints the same file from an installed wheel.
"""
from __future__ import annotations

from pathlib import Path

from ..errors import InputError

_HERE = Path(__file__).resolve().parent


def demo_files() -> tuple[Path, Path]:
    """The shipped 1-DOF replica of the source experiment: (log, ground-truth labels) Parquet paths.

    Made by ``datasets/make_replica.py`` (MuJoCo, seed 0, 330 samples at 20 Hz); its
    ``datasets/README.md`` describes the recording."""
    return _HERE / "replica" / "replica_log.parquet", _HERE / "replica" / "replica_labels.parquet"


def config_files() -> dict[str, Path]:
    """The shipped settings files by name (file stem), e.g. ``{"default": .../default.yaml}``."""
    return {p.stem: p for p in sorted((_HERE / "configs").glob("*.yaml"))}


def config_file(name: str) -> Path:
    """The shipped settings file called ``name`` (with or without ``.yaml``)."""
    files = config_files()
    stem = name[:-5] if name.endswith(".yaml") else name
    if stem not in files:
        raise InputError(f"no shipped settings file '{name}'; shipped: {', '.join(files)}")
    return files[stem]
