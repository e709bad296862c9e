"""ROS 1 and ROS 2 bags, read with ``rosbags`` (no ROS installation needed).

Inputs: a ROS 1 ``.bag`` file; a ROS 2 bag folder (with ``metadata.yaml``) or one of its
``.db3`` / ``.mcap`` files. Topics of type ``sensor_msgs/JointState`` (see :mod:`.joint_states`)
or ``franka_msgs/FrankaState`` (see :mod:`.franka`) are read; the topic is chosen automatically
when the bag has exactly one such topic, else ``--topic`` (or map key ``topic``) names it.

Time: each message's header stamp; map key ``stamp: receive`` takes the time the recorder
received it instead (for publishers that leave the stamp empty or stamp badly). When every
header stamp of the topic is zero (never filled in) the receive time is used, and noted. ``t``
starts at 0; the metadata ``time_origin`` records the stamp of t = 0, the clock and the topic.
The first sample's stamp, when it is a wall clock (Unix time between 2000 and 2100; not a
simulator's time from 0), becomes the log's ``start_time`` (UTC).
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..data.times import wall_clock_iso
from ..errors import InputError
from .base import ConvertedLog
from .franka import FRANKA_FIELDS, franka_log, franka_source
from .joint_states import JointStateMessage, assemble
from .mapping import choice

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
JOINT_STATE = "sensor_msgs/msg/JointState"
FRANKA_STATE = "franka_msgs/msg/FrankaState"
SUPPORTED = (JOINT_STATE, FRANKA_STATE)


def recognises(path: Path, options: dict[str, Any]) -> bool:
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


@contextlib.contextmanager
def open_bag(path: Path) -> Iterator[Any]:
    """An open ``rosbags`` AnyReader; every failure becomes one InputError naming the bag."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError("reading bags needs the 'rosbags' package (pip install rosbags)", file=path) from None

    try:
        # definitions stored in the bag win; the default store only serves bags without any
        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    # rosbags reads a damaged metadata.yaml or storage file with TypeError/AttributeError too
    except (AnyReaderError, OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        kind = "ROS 1 bag" if path.suffix.lower() == ".bag" else "ROS 2 bag"
        raise InputError(f"cannot read as a {kind} ({type(exc).__name__}: {exc})", file=path) from None
    try:
        yield reader
    finally:
        reader.close()


def choose_topic(reader: Any, topic: str | None, path: Path) -> tuple[str, str, list]:
    """(topic, message type, connections) of the topic to convert."""
    try:
        topics = {name: info for name, info in reader.topics.items()}
        connections = list(reader.connections)
    except Exception as exc:  # rosbags lists them from the metadata: a damaged one fails here, any type
        raise InputError(f"cannot list the bag's topics ({type(exc).__name__}: {exc})", file=path) from None
    usable = {name: info.msgtype for name, info in topics.items() if info.msgtype in SUPPORTED}
    if topic is not None:
        if topic not in topics:
            raise InputError(f"topic '{topic}' is not in the bag; it has {sorted(topics)}", file=path)
        if topic not in usable:
            raise InputError(f"topic '{topic}' has type {topics[topic].msgtype}; expected one of "
                             f"{list(SUPPORTED)}", file=path)
    elif len(usable) == 1:
        topic = next(iter(usable))
    else:
        listing = ", ".join(f"{k} ({v})" for k, v in sorted(usable.items())) or "none"
        raise InputError(f"{len(usable)} topics with joint states ({listing}); expected exactly one, "
                         "or name one with --topic", file=path)
    conns = [c for c in connections if c.topic == topic]
    return topic, usable[topic], conns


def _stamp(msg: Any) -> int:
    s = msg.header.stamp
    return int(s.sec) * 1_000_000_000 + int(s.nanosec)


def _messages(reader: Any, conns: list, use_receive: bool) -> tuple[list[tuple[int, int, Any]], bool]:
    """[(stamp ns, receive ns, message)] in bag order, and whether the receive time was used."""
    out = []
    for conn, receive_ns, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        out.append((_stamp(msg), int(receive_ns), msg))
    unset = bool(out) and all(s == 0 for s, _, _ in out)
    if use_receive or unset:
        out = [(r, r, m) for _, r, m in out]
    return out, unset and not use_receive


def _joint_state_log(items, options, path: Path, topic: str) -> ConvertedLog:
    messages = [JointStateMessage(stamp, tuple(m.name), np.asarray(m.position, dtype=np.float64),
                                  np.asarray(m.velocity, dtype=np.float64), np.asarray(m.effort, dtype=np.float64))
                for stamp, _, m in items]
    return assemble(messages, options, options.get("robot"), path, path.stem,
                    f"sensor_msgs/JointState topic {topic} of {path.name}")


def _franka_log(items, options, path: Path, topic: str) -> ConvertedLog:
    stamps = np.array([s for s, _, _ in items], dtype=np.int64)
    fields = {f: np.stack([np.asarray(getattr(m, f), dtype=np.float64) for _, _, m in items])
              for f in FRANKA_FIELDS if hasattr(items[0][2], f)}
    return franka_log(path.stem, (stamps - stamps.min()) * 1e-9, fields, options,
                      franka_source(path, f"topic {topic}"), [f"t = stamp - {int(stamps.min())} ns"], path,
                      start_time=wall_clock_iso(ns=int(stamps.min()))).with_time_origin(stamp_ns=int(stamps.min()))


def read(path: Path, options: dict[str, Any]) -> list[ConvertedLog]:
    """One log from the joint-state topic of a bag."""
    use_receive = choice(options, "stamp", ("header", "receive"), "header") == "receive"
    with open_bag(path) as reader:
        topic, msgtype, conns = choose_topic(reader, options.get("topic"), path)
        try:
            items, fell_back = _messages(reader, conns, use_receive)
        except Exception as exc:  # rosbags raises its own error types per storage/serialisation
            raise InputError(f"topic {topic}: cannot deserialize ({type(exc).__name__}: {exc})",
                             file=path) from None
    if not items:
        raise InputError(f"topic {topic} has no messages", file=path)
    log = (_joint_state_log if msgtype == JOINT_STATE else _franka_log)(items, options, path, topic)
    if use_receive or fell_back:
        log = log.noted("time = recording (receive) time" + (": every header stamp was zero" if fell_back else ""))
    # where t = 0 lies on the bag's clock, for mmgp annotate (docs/annotate.md)
    return [log.with_time_origin(clock="receive" if use_receive or fell_back else "header", topic=topic,
                                 bag=path.name)]
