"""``mmgp annotate``: a copy of a robot recording with mmgp's labels as one more topic.

Every message of the input bag is copied raw (same bytes, same receive time, same connection
definitions); one message per labelled sample is added on ``/mmgp/labels``, of type
``mmgp_msgs/msg/Label`` (:data:`LABEL_DEF`, its definition stored in the bag like every other
type's, so Foxglove, PlotJuggler and rosbags decode it without a ROS package).

Time: a label's ``header.stamp`` is the stamp of the sample it labels (the joint-state message's
header stamp, or its receive time when the log was made on that clock) and its receive time is
that message's receive time, so the labels line up with the joint states whichever clock a viewer
plots on. The log's ``t`` starts at 0; its metadata ``time_origin`` (written by ``mmgp convert``)
gives the stamp of t = 0, the clock and the topic. Logs converted before that metadata existed
still carry the note ``t = stamp - N ns``, which is used instead. Each label row is matched to
the sample message with that stamp (to 1 us: the float ``t`` of a long recording may miss the
nanosecond); a row that matches none is refused (the run was not trained on this bag).

Outputs: a ROS 1 bag is copied to a ``.bag`` file; a ROS 2 bag to a ``.mcap`` or ``.db3`` file
(that storage) or to a bag folder (the input's storage). Complete or absent; the input is only read.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import InputError, describe
from .rosbag import _stamp, choose_topic, open_bag

LABEL_TOPIC = "/mmgp/labels"
LABEL_TYPE = "mmgp_msgs/msg/Label"
LABEL_DEF = "std_msgs/Header header\nbool disturbed\nfloat64 p_disturbed\nint32 mode\n"
LABEL_COLUMNS = ("t", "mode", "disturbed", "p_disturbed")
MATCH_NS = 1000
_NOTE_ORIGIN = re.compile(r"t = stamp - (-?\d+) ns")


@dataclass(frozen=True)
class TimeOrigin:
    """Where a log's t = 0 lies on its recording's clock (see the module doc)."""

    stamp_ns: int
    clock: str = "header"
    topic: str | None = None
    bag: str | None = None


@dataclass(frozen=True)
class Annotated:
    """What :func:`annotate` wrote: ``out``, ``n_labels`` label messages stamped as the samples
    of ``topic``, ``n_copied`` messages copied, and the labelled stretch ``first_ns``..``last_ns``."""

    out: Path
    n_labels: int
    n_copied: int
    topic: str
    first_ns: int
    last_ns: int


def time_origin(log: str | os.PathLike) -> TimeOrigin:
    """The time origin a converted log records (metadata ``time_origin``, else its note)."""
    import pyarrow.parquet as pq

    log = Path(log)
    try:
        meta = {k.decode(errors="replace"): v.decode(errors="replace")
                for k, v in (pq.read_schema(log).metadata or {}).items()}
    except Exception as exc:  # a CSV log, a damaged file: no metadata to read
        raise InputError(f"cannot read the log's Parquet metadata ({describe(exc)}); annotate needs the "
                         "log that 'mmgp convert' wrote from the bag", file=log) from None
    if "time_origin" in meta:
        try:
            d = json.loads(meta["time_origin"])
            return TimeOrigin(int(d["stamp_ns"]), str(d.get("clock", "header")), d.get("topic"), d.get("bag"))
        except (ValueError, TypeError, KeyError):
            raise InputError("metadata 'time_origin' is not a JSON object with an integer 'stamp_ns'",
                             file=log) from None
    found = _NOTE_ORIGIN.search(meta.get("notes", ""))
    if found is None:
        raise InputError("the log records no time origin (metadata 'time_origin' or the note 't = stamp - N "
                         "ns' of 'mmgp convert'): its t cannot be placed on the bag's clock", file=log)
    clock = "receive" if "time = recording (receive) time" in meta["notes"] else "header"
    return TimeOrigin(int(found.group(1)), clock)


def _resolve(name: str, run_dir: Path) -> Path | None:
    """A log path as report.json stores it (as given to train): from here, else from the run."""
    p = Path(name)
    for cand in (p, run_dir / p, run_dir.parent / p) if not p.is_absolute() else (p,):
        if cand.is_file():
            return cand
    return None


def _run_log(run_dir: Path, bag: Path, log: Path | None) -> tuple[Path, int | None]:
    """The log the run's labels of ``bag`` came from, and its index among the run's logs (None: one log)."""
    report = run_dir / "report.json"
    try:
        names = [str(s) for s in json.loads(report.read_text())["logs"]] if report.is_file() else []
    except (ValueError, KeyError, TypeError, OSError) as exc:
        raise InputError(f"unreadable report.json ({describe(exc)})", file=report) from None
    if log is not None:
        if len(names) <= 1:
            return log, None
        hits = [i for i, s in enumerate(names) if Path(s).name == log.name]
        if len(hits) != 1:
            raise InputError(f"--log {log.name}: the run was trained on {names}; name one of them", file=run_dir)
        return log, hits[0]
    paths = [_resolve(s, run_dir) for s in names]
    if len(paths) == 1 and paths[0] is not None:
        return paths[0], None
    mine = [i for i, p in enumerate(paths) if p is not None and _origin_or_none(p, bag.name)]
    if len(mine) == 1:
        return paths[mine[0]], (mine[0] if len(paths) > 1 else None)
    listing = names or "none (no report.json)"
    raise InputError(f"cannot tell which log of the run was converted from {bag.name} (report.json names "
                     f"{listing}, looked up from here, the run's folder and the folder above); give it with "
                     "--log LOG", file=run_dir)


def _origin_or_none(log: Path, bag_name: str) -> bool:
    with contextlib.suppress(InputError):
        return time_origin(log).bag == bag_name
    return False


def read_labels(run_dir: Path, index: int | None):
    """The rows of labels.parquet (of log ``index`` when the run has several) with the columns used."""
    import pandas as pd

    path = run_dir / "labels.parquet"
    try:
        df = pd.read_parquet(path)
    except Exception as exc:
        raise InputError(f"unreadable labels file ({describe(exc)})", file=path) from None
    missing = [c for c in LABEL_COLUMNS if c not in df.columns]
    if missing:
        raise InputError(f"columns {missing} missing; expected {list(LABEL_COLUMNS)}", file=path)
    if "log" in df.columns:
        if index is None:
            raise InputError("the labels are of several logs (column 'log'): give the bag's with --log", file=path)
        df = df[df["log"] == index]
    if df.empty:
        raise InputError("no label rows for this log", file=path)
    return df


def _samples(reader: Any, origin: TimeOrigin, path: Path) -> tuple[str, np.ndarray, np.ndarray]:
    """(topic, sorted unique stamps on the log's clock, the receive time of each) of the sampled topic."""
    topic, _, conns = choose_topic(reader, origin.topic, path)
    stamps, receive = [], []
    try:
        for conn, rec, raw in reader.messages(connections=conns):
            stamps.append(int(rec) if origin.clock == "receive" else _stamp(reader.deserialize(raw, conn.msgtype)))
            receive.append(int(rec))
    except Exception as exc:  # rosbags raises its own error types per storage/serialisation
        raise InputError(f"topic {topic}: cannot deserialize ({describe(exc)})", file=path) from None
    if not stamps:
        raise InputError(f"topic {topic} has no messages", file=path)
    stamps, receive = np.array(stamps, dtype=np.int64), np.array(receive, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    uniq, first = np.unique(stamps[order], return_index=True)
    return topic, uniq, receive[order][first]


def match_labels(t: np.ndarray, origin: TimeOrigin, topic: str, stamps: np.ndarray, receive: np.ndarray,
                 file: Path) -> tuple[np.ndarray, np.ndarray]:
    """(header stamp, receive time) in ns of the sample each label time ``t`` (s) labels."""
    want = origin.stamp_ns + np.rint(np.asarray(t, dtype=np.float64) * 1e9).astype(np.int64)
    if want.max() < stamps[0] - MATCH_NS or want.min() > stamps[-1] + MATCH_NS:
        raise InputError(f"the labels cover stamps {want.min()} .. {want.max()} ns but topic {topic} spans "
                         f"{stamps[0]} .. {stamps[-1]} ns: no overlap (labels of another recording?)", file=file)
    right = np.clip(np.searchsorted(stamps, want), 0, len(stamps) - 1)
    left = np.clip(right - 1, 0, len(stamps) - 1)
    near = np.where(np.abs(stamps[left] - want) <= np.abs(stamps[right] - want), left, right)
    off = np.abs(stamps[near] - want)
    if (off > MATCH_NS).any():
        k = int(np.flatnonzero(off > MATCH_NS)[0])
        raise InputError(f"label row {k} (t = {t[k]:.9f} s, stamp {want[k]} ns) matches no message of topic "
                         f"{topic} (nearest {int(off[k])} ns away): the run's log was not converted from "
                         "this bag", file=file, row=k)
    return stamps[near], receive[near]


def _store(ros1: bool):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    store.register(get_types_from_msg(LABEL_DEF, LABEL_TYPE))
    return store


def label_messages(labels, header_ns: np.ndarray, receive_ns: np.ndarray, ros1: bool) -> tuple[Any, list]:
    """(type store with the label type, [(receive ns, serialized message)] in receive order)."""
    store = _store(ros1)
    Header, Time, Label = (store.types[n] for n in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time", LABEL_TYPE))
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    out = []
    rows = zip(header_ns, receive_ns, labels["disturbed"].to_numpy(), labels["p_disturbed"].to_numpy(),
               labels["mode"].to_numpy())
    for k, (stamp, rec, disturbed, p, mode) in enumerate(rows):
        time = Time(sec=int(stamp) // 1_000_000_000, nanosec=int(stamp) % 1_000_000_000)
        header = Header(seq=k, stamp=time, frame_id="") if ros1 else Header(stamp=time, frame_id="")
        msg = Label(header=header, disturbed=bool(disturbed == 1), p_disturbed=float(p), mode=int(mode))
        out.append((int(rec), serialize(msg, LABEL_TYPE)))
    out.sort(key=lambda item: item[0])
    return store, out


def output_kind(bag: Path, out: Path) -> tuple[bool, Any, bool]:
    """(ROS 1?, ROS 2 storage plugin or None, a single storage file rather than a folder?) of
    the copy of ``bag`` at ``out``; a mismatch (a ROS 1 bag into .mcap) is refused."""
    suffix = out.suffix.lower()
    if bag.suffix.lower() == ".bag":
        if suffix != ".bag":
            raise InputError("the input is a ROS 1 bag: expected an --out file name ending in .bag", file=out)
        return True, None, True
    from rosbags.rosbag2 import StoragePlugin

    if suffix in (".mcap", ".db3"):
        return False, StoragePlugin.MCAP if suffix == ".mcap" else StoragePlugin.SQLITE3, True
    if suffix == ".bag":
        raise InputError("--out ends in .bag, a ROS 1 bag, but the input is a ROS 2 bag: expected a .mcap or "
                         ".db3 file or a folder", file=out)
    mcap = bag.suffix.lower() == ".mcap" or (bag.is_dir() and any(bag.glob("*.mcap")))
    return False, StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3, False


def _add_ros1(writer, conn):
    from rosbags.rosbag1 import WriterError

    try:
        return writer.add_connection(conn.topic, conn.msgtype, msgdef=conn.msgdef.data, md5sum=conn.digest,
                                     callerid=conn.ext.callerid, latching=conn.ext.latching)
    except WriterError:  # the same connection twice in the input: one in the copy
        return next(c for c in writer.connections if c.topic == conn.topic and c.msgtype == conn.msgtype
                    and c.ext == conn.ext)


def _add_ros2(writer, conn):
    from rosbags.rosbag2 import WriterError
    from rosbags.typesys import Stores, get_typestore

    stored = bool(conn.msgdef.data) and bool(conn.digest)  # old bags store no definitions
    try:
        return writer.add_connection(conn.topic, conn.msgtype, msgdef=conn.msgdef.data if stored else None,
                                     rihs01=conn.digest if stored else None,
                                     typestore=None if stored else get_typestore(Stores.LATEST),
                                     serialization_format=conn.ext.serialization_format,
                                     offered_qos_profiles=conn.ext.offered_qos_profiles)
    except WriterError:
        return next(c for c in writer.connections if c.topic == conn.topic and c.msgtype == conn.msgtype
                    and c.ext == conn.ext)
    except KeyError:
        raise InputError(f"topic {conn.topic}: type {conn.msgtype} has no definition in the bag nor in rosbags' "
                         "type store; it cannot be copied") from None


def _copy(reader: Any, writer, add, store, labels: list) -> int:
    """Every message of ``reader`` into ``writer`` raw, the labels merged in by receive time
    (a label after the sample it labels); returns the number of messages copied."""
    conns = {conn.id: add(writer, conn) for conn in reader.connections}
    target = writer.add_connection(LABEL_TOPIC, LABEL_TYPE, typestore=store)
    pending = iter(labels)
    nxt = next(pending, None)
    n = 0
    for conn, rec, raw in reader.messages():
        while nxt is not None and nxt[0] < rec:
            writer.write(target, *nxt)
            nxt = next(pending, None)
        writer.write(conns[conn.id], rec, raw)
        n += 1
    while nxt is not None:
        writer.write(target, *nxt)
        nxt = next(pending, None)
    return n


@contextlib.contextmanager
def _bag_writer(bag: Path, out: Path, force: bool) -> Iterator[Any]:
    """An open rosbags writer whose bag becomes ``out`` only when the block finishes."""
    from ..data.outputs import atomic_output_dir, atomic_output_file

    ros1, storage, single = output_kind(bag, out)
    if ros1:
        from rosbags.rosbag1 import Writer

        with atomic_output_file(out, force=force, inputs=[bag]) as tmp:
            tmp.unlink()  # rosbags writes new files only
            with Writer(tmp) as writer:
                yield writer
        return
    from rosbags.rosbag2 import Writer

    opened = atomic_output_file(out, force=force, inputs=[bag]) if single else \
        atomic_output_dir(out, force=force, inputs=[bag])
    with opened as tmp:
        # rosbags writes a folder DIR holding DIR/<DIR name>.db3 or .mcap and metadata.yaml
        folder = tmp.parent / f"{tmp.name}.bag" if single else tmp / out.name
        try:
            with Writer(folder, version=9, storage_plugin=storage) as writer:
                yield writer
            if single:
                os.replace(folder / f"{folder.name}{out.suffix.lower()}", tmp)
            else:
                for f in list(folder.iterdir()):  # metadata.yaml names <out.name>.<storage>: still right
                    os.replace(f, tmp / f.name)
        finally:
            shutil.rmtree(folder, ignore_errors=True)


def _inside(child: Path, parent: Path) -> bool:
    child, parent = child.resolve(), parent.resolve()
    return child == parent or parent in child.parents


def annotate(run_dir: str | os.PathLike, bag: str | os.PathLike, out: str | os.PathLike, *,
             log: str | os.PathLike | None = None, force: bool = False) -> Annotated:
    """Write ``out``: the bag ``bag`` with the labels of the training run ``run_dir`` on
    ``/mmgp/labels`` (see the module doc). ``log``: the log the run was trained on, when
    report.json's path does not lead to it. Raises :class:`mmgp.errors.InputError`."""
    from ..data.outputs import check_output

    run_dir, bag, out = Path(run_dir), Path(bag), Path(out)
    if not (run_dir / "labels.parquet").is_file():
        raise InputError("labels.parquet missing: expected the output folder of 'mmgp train'", file=run_dir)
    if _inside(out, bag):
        raise InputError("--out is or lies inside the input bag: inputs are never modified", file=out)
    ros1, _, single = output_kind(bag, out)
    check_output(out, force=force, inputs=[bag], folder=not single)  # before any work
    log_path, index = _run_log(run_dir, bag, None if log is None else Path(log))
    labels = read_labels(run_dir, index)
    origin = time_origin(log_path)
    with open_bag(bag) as reader:
        topic, stamps, receive = _samples(reader, origin, bag)
        header_ns, receive_ns = match_labels(labels["t"].to_numpy(), origin, topic, stamps, receive,
                                             run_dir / "labels.parquet")
        store, messages = label_messages(labels, header_ns, receive_ns, ros1)
        with _bag_writer(bag, out, force) as writer:
            try:
                n = _copy(reader, writer, _add_ros1 if ros1 else _add_ros2, store, messages)
            except InputError as exc:
                raise (InputError(exc.message, file=bag) if exc.file is None else exc) from None
            except Exception as exc:  # rosbags' reader and writer errors, any type
                raise InputError(f"cannot copy the bag ({describe(exc)})", file=bag) from None
    return Annotated(out, len(messages), n, topic, int(header_ns.min()), int(header_ns.max()))
