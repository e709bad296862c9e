"""Which reader reads an input: chosen by the map's ``format``, else by content and file name."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..errors import InputError
from . import datasets, mapped_csv, ros_csv, rosbag, rtde
from .base import ConvertedLog
from .mapping import map_file
from .tables import header_names


@dataclass(frozen=True)
class Reader:
    """``name`` is the map's ``format`` value; ``expects`` says what it reads (for errors)."""

    name: str
    expects: str
    recognises: Callable[[Path, dict], bool]
    read: Callable[[Path, dict], list[ConvertedLog]]


def _recognises_contract(path: Path, options: dict[str, Any]) -> bool:
    if not path.is_file():
        return False
    if path.suffix.lower() in (".parquet", ".pq"):
        return True
    names = header_names(path)
    return "t" in names and "q_0" in names and "tau_0" in names


def _read_contract(path: Path, options: dict[str, Any]) -> list[ConvertedLog]:
    from ..data.logs import read_log

    log = read_log(path, min_samples=1)
    return [ConvertedLog.of(name=path.stem, t=log.t, q=log.q, tau=log.tau, dq=log.dq, ddq=log.ddq,
                         joint_names=log.joint_names, robot=log.metadata.get("robot"), file=path,
                         source=f"contract log {path.name}", notes=[], start_time=log.metadata.get("start_time"))]


# In this order: a map with columns means a plain CSV whatever else the file looks like.
READERS = (
    Reader("csv", "a CSV/text table with a column map (--map with 'columns')",
           mapped_csv.recognises, mapped_csv.read),
    Reader("rosbag", "a ROS 1 .bag, or a ROS 2 bag folder (metadata.yaml) / .db3 / .mcap, with a "
           "sensor_msgs/JointState or franka_msgs/FrankaState topic", rosbag.recognises, rosbag.read),
    Reader("dataset", "a shared dataset folder (" + ", ".join(d.name for d in datasets.DATASETS) + ")",
           datasets.recognises, datasets.read),
    Reader("rtde", "a UR RTDE CSV (timestamp, actual_q_0 .., and a torque field)", rtde.recognises, rtde.read),
    Reader("franka_csv", "a CSV export of franka_msgs/FrankaState (field.q0 .., field.tau_J0 ..)",
           ros_csv.recognises_franka, ros_csv.read_franka),
    Reader("joint_states_csv", "a CSV export of sensor_msgs/JointState (field.name0 .., field.position0 .., "
           "field.effort0 ..)", ros_csv.recognises_joint_states, ros_csv.read_joint_states),
    Reader("contract", "a contract log (t, q_0 .., tau_0 ..; Parquet or CSV)", _recognises_contract, _read_contract),
)


def pick_reader(path: Path, options: dict[str, Any]) -> Reader:
    """The reader for ``path``: the map's ``format``, else the first that recognises it."""
    if not path.exists():
        raise InputError("input does not exist", file=path)
    fmt = options.get("format")
    if fmt is not None:
        by_name = {r.name: r for r in READERS}
        if fmt not in by_name:
            raise InputError(f"map key 'format' must be one of {list(by_name)}, found {fmt!r}",
                             file=map_file(options), column="format")
        return by_name[fmt]
    for reader in READERS:
        if reader.recognises(path, options):
            return reader
    raise InputError("no reader recognises this input; expected one of: "
                     + "; ".join(r.expects for r in READERS), file=path)
