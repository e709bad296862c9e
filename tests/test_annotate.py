"""``mmgp annotate``: bags written here with rosbags (ROS 1, ROS 2 sqlite3, ROS 2 MCAP), converted
with ``mmgp convert``, labelled by a hand-written labels.parquet, annotated through the command
line and read back with rosbags: one label message per label row, stamped with the stamps this
test wrote (to the nanosecond), field values equal to the labels file, every original message
byte-identical, the input untouched; and the refusals, one line each with exit status 2."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.convert import convert

runner = CliRunner()
JOINTS = ["j1", "j2", "j3"]
T0_NS = 1_700_000_000_123_456_789
JS, STR = "sensor_msgs/msg/JointState", "std_msgs/msg/String"
CASES = {"ros1": ("run.bag", "labelled.bag"), "db3": ("run", "labelled"), "mcap": ("run/run.mcap", "labelled.mcap")}


def _stamp(store, ns: int):
    return store.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def write_bag(folder: Path, case: str, T: int = 30, seed: int = 0) -> dict:
    """A JointState stream (header stamps != receive times) and an unrelated String topic.
    Returns the bag path and what was written: stamps, receive times, [(topic, receive, bytes)]."""
    ros1 = case == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    rng = np.random.default_rng(seed)
    stamps = T0_NS + np.arange(T, dtype=np.int64) * 10_000_000 + rng.integers(0, 1000, T)
    receive = stamps + 2_000_000 + rng.integers(0, 500_000, T)  # the recorder gets them later
    written = []
    for k in range(T):
        head = dict(stamp=_stamp(store, int(stamps[k])), frame_id="")
        Header = store.types["std_msgs/msg/Header"]
        header = Header(seq=k, **head) if ros1 else Header(**head)
        msg = store.types[JS](header=header, name=JOINTS, position=rng.normal(size=3), velocity=rng.normal(size=3),
                              effort=rng.normal(size=3))
        written.append(("/joint_states", JS, int(receive[k]), serialize(msg, JS)))
    for k in range(7):  # an unrelated topic, interleaved with the samples
        chat = store.types[STR](data=f"note {k}")
        written.append(("/chatter", STR, int(T0_NS + 3_000_000 + k * 41_000_000), serialize(chat, STR)))
    written.sort(key=lambda w: w[2])
    path = folder / CASES[case][0]
    root = path if case != "mcap" else path.parent
    writer = Writer1(root) if ros1 else Writer2(root, version=9, storage_plugin=StoragePlugin.MCAP if case == "mcap"
                                                else StoragePlugin.SQLITE3)
    with writer as w:
        conns = {t: w.add_connection(t, mt, typestore=store) for t, mt in (("/joint_states", JS), ("/chatter", STR))}
        for topic, _, rec, raw in written:
            w.write(conns[topic], rec, raw)
    if case == "mcap":
        assert path.is_file()
    return {"bag": path, "stamps": stamps, "receive": receive,
            "messages": [(topic, rec, bytes(raw)) for topic, _, rec, raw in written]}


def digest(path: Path) -> str:
    h = hashlib.sha256()
    for f in sorted(path.rglob("*")) if path.is_dir() else [path]:
        if f.is_file():
            h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()


def make_run(folder: Path, log: Path, rows: np.ndarray, seed: int = 1,
             shift_s: float = 0.0) -> tuple[Path, pd.DataFrame]:
    """A training run's folder by hand: labels of log rows ``rows`` (t as training copies it from the log)."""
    rng = np.random.default_rng(seed)
    t = pd.read_parquet(log)["t"].to_numpy()[rows] + shift_s
    labels = pd.DataFrame({"t": t, "mode": rng.integers(0, 3, len(t)), "disturbed": rng.integers(0, 2, len(t)),
                           "p_disturbed": rng.random(len(t)), "p_mode_0": rng.random(len(t))})
    run = folder / "run_dir"
    run.mkdir()
    labels.to_parquet(run / "labels.parquet", index=False)
    (run / "report.json").write_text(json.dumps({"logs": [str(log)]}))
    return run, labels


def read_back(path: Path):
    """[(topic, receive, raw bytes, message or None)] of a bag, in the order read."""
    out = []
    with AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as reader:
        for conn, rec, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype) if conn.topic == "/mmgp/labels" else None
            out.append((conn.topic, int(rec), bytes(raw), msg, conn.msgtype))
        # the label type's definition is stored in the bag (no ROS package needed to decode it)
        (label,) = [c for c in reader.connections if c.topic == "/mmgp/labels"]
        assert "float64 p_disturbed" in label.msgdef.data and "int32 mode" in label.msgdef.data
    return out


def annotated(tmp_path: Path, case: str, map_text: str | None = None):
    data = write_bag(tmp_path, case)
    map_path = None
    if map_text is not None:
        map_path = tmp_path / "map.yaml"
        map_path.write_text(map_text)
    (log,) = convert(data["bag"], tmp_path / "log.parquet", map_path=map_path)
    rows = np.arange(0, len(data["stamps"]), 2)  # every other sample, as a downsampled run labels
    run, labels = make_run(tmp_path, log, rows)
    before = digest(data["bag"])
    out = tmp_path / CASES[case][1]
    res = runner.invoke(app, ["annotate", str(run), str(data["bag"]), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert digest(data["bag"]) == before
    return data, rows, labels, out, res


@pytest.mark.parametrize("case", list(CASES))
def test_labels_topic_stamped_as_the_samples_and_everything_else_copied(tmp_path, case):
    data, rows, labels, out, res = annotated(tmp_path, case)
    assert out.is_dir() == (case == "db3")
    got = read_back(out)
    marks = [g for g in got if g[0] == "/mmgp/labels"]
    assert len(marks) == len(labels) == len(rows)
    assert {g[4] for g in marks} == {"mmgp_msgs/msg/Label"}
    for (_, rec, _, msg, _), k, (_, row) in zip(marks, rows, labels.iterrows()):
        assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == data["stamps"][k]
        assert rec == data["receive"][k]
        assert msg.disturbed == bool(row["disturbed"]) and type(msg.disturbed) is bool
        assert msg.p_disturbed == row["p_disturbed"]
        assert msg.mode == row["mode"]
    # every original message, same topic, receive time and bytes, in the same order
    assert [(t, r, b) for t, r, b, _, _ in got if t != "/mmgp/labels"] == data["messages"]
    assert f"{len(rows)} labels on /mmgp/labels" in res.output


def test_receive_clock_and_a_log_with_only_the_note(tmp_path):
    # a log made on the recorder's clock: the labels' stamps are the receive times
    data, rows, labels, out, _ = annotated(tmp_path, "db3", map_text="stamp: receive\n")
    marks = [g for g in read_back(out) if g[0] == "/mmgp/labels"]
    assert [m[3].header.stamp.sec * 1_000_000_000 + m[3].header.stamp.nanosec for m in marks] == \
        list(data["receive"][rows])
    assert [m[1] for m in marks] == list(data["receive"][rows])
    # a log converted before metadata 'time_origin' existed: its note 't = stamp - N ns' serves
    log = tmp_path / "log.parquet"
    table = pq.read_table(log)
    meta = {k: v for k, v in table.schema.metadata.items() if k != b"time_origin"}
    pq.write_table(table.replace_schema_metadata(meta), log)
    res = runner.invoke(app, ["annotate", str(tmp_path / "run_dir"), str(data["bag"]), "--out",
                              str(tmp_path / "again.mcap")])
    assert res.exit_code == 0, res.output
    again = [g for g in read_back(tmp_path / "again.mcap") if g[0] == "/mmgp/labels"]
    assert [m[1] for m in again] == list(data["receive"][rows])


def _refused(args, *needles):
    res = runner.invoke(app, ["annotate", *map(str, args)])
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_refusals(tmp_path):
    data = write_bag(tmp_path, "ros1")
    (log,) = convert(data["bag"], tmp_path / "log.parquet")
    run, _ = make_run(tmp_path, log, np.arange(30))
    out = tmp_path / "labelled.bag"
    empty = tmp_path / "empty_run"
    empty.mkdir()
    _refused([empty, data["bag"], "--out", out], "labels.parquet missing")
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag at all")
    _refused([run, junk, "--out", out], "cannot read as a ROS 1 bag", str(junk))
    _refused([run, data["bag"], "--out", tmp_path / "labelled.mcap"], "expected an --out file name ending in .bag")
    _refused([run, data["bag"], "--out", data["bag"]], "inside the input bag")
    far = tmp_path / "far"
    far.mkdir()
    far_run, _ = make_run(far, log, np.arange(30), shift_s=3600.0)  # an hour after the recording
    _refused([far_run, data["bag"], "--out", out], "no overlap")
    assert not out.exists() and not list(tmp_path.glob(".labelled.bag*"))  # nothing left behind
    assert runner.invoke(app, ["annotate", str(run), str(data["bag"]), "--out", str(out)]).exit_code == 0
    _refused([run, data["bag"], "--out", out], "--force")
    assert runner.invoke(app, ["annotate", str(run), str(data["bag"]), "--out", str(out), "--force"]).exit_code == 0
    plain = tmp_path / "plain.csv"
    pd.read_parquet(log).to_csv(plain, index=False)
    (run / "report.json").write_text(json.dumps({"logs": [str(plain)]}))
    _refused([run, data["bag"], "--out", tmp_path / "x.bag"], "Parquet metadata")


def test_run_of_two_logs_takes_the_bags_rows(tmp_path):
    # train on two recordings: labels.parquet has column 'log'; the bag's log is told by its time origin
    mine, other = tmp_path / "mine", tmp_path / "other"
    mine.mkdir(), other.mkdir()
    data = write_bag(mine, "ros1")
    write_bag(other, "ros1", seed=5)
    logs = [convert(f / "run.bag", f / "log.parquet")[0] for f in (other, mine)]
    (other / "run.bag").rename(other / "second.bag")  # the other log came from another bag name
    table = pq.read_table(logs[0])
    origin = {**json.loads(table.schema.metadata[b"time_origin"]), "bag": "second.bag"}
    meta = {**table.schema.metadata, b"time_origin": json.dumps(origin).encode()}
    pq.write_table(table.replace_schema_metadata(meta), logs[0])
    t = [pd.read_parquet(p)["t"].to_numpy() for p in logs]
    labels = pd.DataFrame({"t": np.concatenate(t), "log": np.repeat([0, 1], [len(x) for x in t]),
                           "mode": np.arange(sum(len(x) for x in t)) % 3, "disturbed": 0, "p_disturbed": 0.25})
    run = tmp_path / "run_dir"
    run.mkdir()
    labels.to_parquet(run / "labels.parquet", index=False)
    (run / "report.json").write_text(json.dumps({"logs": [str(p) for p in logs]}))
    out = tmp_path / "labelled.bag"
    res = runner.invoke(app, ["annotate", str(run), str(data["bag"]), "--out", str(out)])
    assert res.exit_code == 0, res.output
    marks = [g for g in read_back(out) if g[0] == "/mmgp/labels"]
    assert [m[1] for m in marks] == list(data["receive"])
    assert [m[3].mode for m in marks] == list(labels["mode"][labels["log"] == 1])
