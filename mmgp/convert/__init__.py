"""Real robot formats into contract logs (CONTRACT section 1): ``mmgp convert`` and its library.

Readers (see :mod:`.registry` for how one is chosen; docs/convert.md for every convention):
ROS 1 / ROS 2 bags (:mod:`.rosbag`), UR RTDE CSV (:mod:`.rtde`), franka_ros FrankaState and
JointState CSV exports (:mod:`.ros_csv`), plain CSV with a column map (:mod:`.mapped_csv`), the
eight shared real-robot datasets (:mod:`.datasets`), and contract logs themselves.

>>> parts = read_input("run.bag", robot="panda")          # doctest: +SKIP
>>> write_logs(parts, "run.parquet", source="run.bag")      # doctest: +SKIP
"""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

from ..data.times import wall_clock_iso
from .base import ConvertedLog, check_log, order_for_robot, order_in_time, select_joints
from .mapping import load_map
from .registry import READERS, Reader, pick_reader
from .writer import write_logs

__all__ = ["ConvertedLog", "READERS", "Reader", "convert", "load_map", "pick_reader", "read_input", "write_logs"]


def _absolute_start(log: ConvertedLog) -> ConvertedLog:
    """A ``t`` column in Unix seconds (a CSV's absolute time column: its first sample after 2000)
    gives the log's ``start_time`` when its reader found none; ``t`` itself is kept."""
    if log.start_time is not None or not log.t.size:
        return log
    start = wall_clock_iso(float(log.t[0]))
    if start is None:
        return log
    return replace(log, metadata=dict(log.metadata, start_time=start)).noted(
        f"t is Unix time: start_time = t[0] = {start}")


def _finish(log: ConvertedLog, options: dict, path: Path) -> ConvertedLog:
    """The conventions shared by every reader, in order: joints, time, robot order, checks."""
    if options.get("joints") and log.joint_names != list(options["joints"]):
        log = select_joints(log, options["joints"], path)
    log = order_in_time(log, path)
    log = _absolute_start(log)
    if options.get("robot"):
        log = order_for_robot(log, options["robot"], path)
    check_log(log, path)
    return log


def read_input(path: str | os.PathLike, *, robot: str | None = None, map_path: str | os.PathLike | None = None,
               topic: str | None = None) -> list[ConvertedLog]:
    """Read ``path`` (file or folder) into checked contract logs, without writing anything.

    ``robot`` (example-robot-data name) orders joints as the model does and names the robot in
    the metadata; ``map_path`` is the YAML map (:mod:`.mapping`); ``topic`` picks a bag topic.
    Flags win over the same keys in the map. Raises :class:`mmgp.errors.InputError`.
    """
    path = Path(path)
    options = load_map(map_path)
    if robot is not None:
        options["robot"] = robot
    if topic is not None:
        options["topic"] = topic
    reader = pick_reader(path, options)
    return [_finish(log, options, path) for log in reader.read(path, options)]


def convert(path: str | os.PathLike, out: str | os.PathLike, *, robot: str | None = None,
            map_path: str | os.PathLike | None = None, topic: str | None = None, part: str | None = None,
            force: bool = False) -> list[Path]:
    """Read ``path`` and write its log(s) to ``out`` (a .parquet/.csv file, or a folder for all
    parts); returns the files written. See :func:`read_input` and :func:`write_logs`."""
    return write_logs(read_input(path, robot=robot, map_path=map_path, topic=topic), out,
                      source=path, part=part, force=force)
