"""The eight public real-robot datasets of the shared folder (each folder has a SOURCE.md).

A folder is recognised by the files it holds (the names its SOURCE.md lists), wherever it lives:
``mmgp convert <path>/ias_nguyen_tuong --out DIR``. One of a folder's files may be given instead
when the folder has its SOURCE.md (e.g. ``ias_nguyen_tuong/ias_real_barrett_data.mat`` for that
robot's two splits only).
Options of the converters come from the map's ``dataset`` key; conventions are in the two modules.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Callable

from ...errors import InputError
from ..base import ConvertedLog
from ..mapping import map_file
from . import mat_sets, text_sets

Read = Callable[[Path, "Path | None", dict], list[ConvertedLog]]


@dataclass(frozen=True)
class Dataset:
    """One shared dataset: the files that identify it, its options and its converter."""

    name: str
    markers: tuple[str, ...]
    options: tuple[str, ...]
    read: Read


DATASETS = (
    Dataset("ias_nguyen_tuong", tuple(mat_sets.IAS_FILES.values()), ("drop_test_duplicates",), mat_sets.read_ias),
    Dataset("sarcos", ("sarcos_inv_test.mat",), (), mat_sets.read_sarcos),
    Dataset("polydoros_ur10_pickplace", ("URpickNplace.mat",), ("fix_ddq",), mat_sets.read_ur10),
    Dataset("polydoros_baxter_forward", ("BaxterDirectDynamics.mat",), (), mat_sets.read_baxter),
    Dataset("panda_gaz2019", ("rbt_log/exciting_traj_positions.txt",), (), text_sets.read_panda),
    Dataset("staubli_tx40_figaroh", ("pos_read_data.csv", "curr_data.csv"), (), text_sets.read_staubli),
    Dataset("tiago_figaroh", ("tiago_position.csv", "tiago_effort.csv"), ("raw_effort",), text_sets.read_tiago),
    Dataset("iiwa14_lasa_subset", ("gprProcessedActualData.csv",), ("flip_tau",), text_sets.read_iiwa),
)


def identify(path: Path) -> tuple[Dataset, Path, Path | None] | None:
    """(dataset, its folder, the one file asked for or None), or None when not a shared dataset."""
    if path.is_dir():
        hits = [d for d in DATASETS if any((path / m).is_file() for m in d.markers)]
        if len(hits) > 1:
            raise InputError(f"the folder holds files of several datasets: {[d.name for d in hits]}", file=path)
        return (hits[0], path, None) if hits else None
    for d in DATASETS:
        for marker in d.markers:
            parts = PurePosixPath(marker).parts
            if path.name == parts[-1] and path.parent.parts[len(path.parent.parts) - len(parts) + 1:] == parts[:-1]:
                folder = path.parents[len(parts) - 1]
                # a lone file is only taken for a dataset's when its folder says so (SOURCE.md)
                if (folder / "SOURCE.md").is_file():
                    return d, folder, path
    return None


def recognises(path: Path, options: dict[str, Any]) -> bool:
    return identify(path) is not None


def read(path: Path, options: dict[str, Any]) -> list[ConvertedLog]:
    """The logs of a shared-dataset folder (or of the one file of it given)."""
    found = identify(path)
    if found is None:
        raise InputError("not one of the shared datasets: expected a folder holding "
                         + "; ".join(f"{d.name}: {', '.join(d.markers)}" for d in DATASETS), file=path)
    dataset, folder, file = found
    opts = options.get("dataset", {})
    unknown = sorted(str(k) for k in opts if k not in dataset.options)
    if unknown:
        raise InputError(f"dataset option(s) {unknown} do not apply to {dataset.name}; its options: "
                         f"{list(dataset.options) or 'none'}", file=map_file(options), column="dataset")
    bad = [k for k, v in opts.items() if not isinstance(v, bool)]
    if bad:
        raise InputError(f"dataset option(s) {bad} must be true or false", file=map_file(options), column="dataset")
    # a file of a multi-file dataset selects itself only where that means something (IAS)
    return dataset.read(folder, file if dataset.name == "ias_nguyen_tuong" else None, opts)
