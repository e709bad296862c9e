"""ROS 1 and ROS 2 bags written here with rosbags' writer, converted, and compared with what was
written: values, joint order, time stamps, and the refusals (mixed joint sets, clashing stamps,
unreadable bags) through the command line."""
from __future__ import annotations

import hashlib
import json
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.convert import convert, read_input
from mmgp.data.logs import read_log
from mmgp.errors import InputError

runner = CliRunner()
ARM = [f"panda_joint{i}" for i in range(1, 8)]
FINGERS = ["panda_finger_joint1", "panda_finger_joint2"]
T0_NS = 1_700_000_000_123_456_789  # an epoch stamp: its ns digits must survive
JS = "sensor_msgs/msg/JointState"
FRANKA = "franka_msgs/msg/FrankaState"
# franka_msgs/FrankaState reduced to the fields the converter reads (the real one has more)
FRANKA_DEF = "std_msgs/Header header\nfloat64[7] q\nfloat64[7] dq\nfloat64[7] tau_J\nfloat64[7] tau_J_d\nfloat64 time\n"


def _store(ros1: bool):
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(FRANKA_DEF, FRANKA))
    return store


def _header(store, ros1: bool, stamp_ns: int):
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return Header(seq=0, stamp=stamp, frame_id="") if ros1 else Header(stamp=stamp, frame_id="")


def joint_state(store, ros1, stamp_ns, names, pos, vel, eff):
    return store.types[JS](header=_header(store, ros1, stamp_ns), name=list(names), position=np.asarray(pos, float),
                           velocity=np.asarray(vel, float), effort=np.asarray(eff, float))


def write_bag(path: Path, ros1: bool, topics: dict[str, list[tuple[int, str, object]]], store,
              storage=StoragePlugin.SQLITE3) -> Path:
    """topics: name -> [(receive ns, msgtype, message)] written in list order."""
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    writer = Writer1(path) if ros1 else Writer2(path, version=9, storage_plugin=storage)
    with writer as w:
        for topic, items in topics.items():
            conn = w.add_connection(topic, items[0][1], typestore=store)
            for receive, msgtype, msg in items:
                w.write(conn, receive, serialize(msg, msgtype))
    return path


def sample_data(T=40, n=7, seed=0):
    rng = np.random.default_rng(seed)
    stamps = T0_NS + np.arange(T, dtype=np.int64) * 10_000_000 + rng.integers(0, 1000, T)
    return stamps, rng.normal(size=(T, n)), rng.normal(size=(T, n)), rng.normal(scale=5, size=(T, n))


def arm_messages(store, ros1, stamps, q, dq, tau, names=ARM, order=None):
    """One message per row; ``order[k]`` permutes the joints of message k."""
    out = []
    for k, s in enumerate(stamps):
        p = np.arange(len(names)) if order is None else order[k]
        out.append((int(s) + 500, JS, joint_state(store, ros1, int(s), [names[i] for i in p], q[k, p], dq[k, p],
                                                  tau[k, p])))
    return out


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_joint_state_bag_values(tmp_path, ros1):
    store = _store(ros1)
    stamps, q, dq, tau = sample_data()
    bag = write_bag(tmp_path / ("run.bag" if ros1 else "run"), ros1,
                    {"/joint_states": arm_messages(store, ros1, stamps, q, dq, tau)}, store)
    (out,) = convert(bag, tmp_path / "log.parquet")
    log = read_log(out)
    np.testing.assert_array_equal(log.q, q)
    np.testing.assert_array_equal(log.dq, dq)
    np.testing.assert_array_equal(log.tau, tau)
    assert log.ddq is None
    # t from the header stamps, origin subtracted exactly in integer ns
    np.testing.assert_allclose(log.t, (stamps - stamps[0]) * 1e-9, rtol=0, atol=1e-15)
    assert log.joint_names == ARM
    assert pq.read_schema(out).metadata[b"notes"].decode().startswith(f"t = stamp - {stamps[0]} ns")


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP], ids=["db3", "mcap"])
def test_ros2_robot_order_late_and_repeated_messages(tmp_path, storage):
    store = _store(False)
    stamps, q, dq, tau = sample_data(seed=1)
    rng = np.random.default_rng(2)
    order = [rng.permutation(7) for _ in stamps]  # every message lists the joints differently
    items = arm_messages(store, False, stamps, q, dq, tau, order=order)
    items[5] = (int(stamps[6]) + 900, JS, items[5][2])  # stamped before message 6, recorded after it
    items.insert(20, items[20])  # a message recorded twice
    bag = write_bag(tmp_path / "run", False, {"/joint_states": items}, store, storage)
    (log,) = read_input(bag, robot="panda")
    np.testing.assert_array_equal(log.q, q)  # model order, sorted in time, repeat dropped
    np.testing.assert_array_equal(log.tau, tau)
    assert log.joint_names == ARM and log.robot == "panda"
    assert any("sorted" in n for n in log.notes) and any("repeats" in n for n in log.notes)
    (file_log,) = read_input(next(bag.glob("*.db3" if storage == StoragePlugin.SQLITE3 else "*.mcap")))
    # the storage file alone reads too; without --robot the columns follow the first message
    assert file_log.joint_names == [ARM[i] for i in order[0]]
    np.testing.assert_array_equal(file_log.q, q[:, order[0]])


def test_mixed_joint_sets_refused_or_chosen(tmp_path):
    store = _store(True)
    stamps, q, dq, tau = sample_data()
    arm = arm_messages(store, True, stamps, q, dq, tau)
    grip = [(int(s) + 700, JS, joint_state(store, True, int(s) + 3, FINGERS, [0.01, 0.01], [0, 0], [1, 1]))
            for s in stamps]
    bag = write_bag(tmp_path / "mixed.bag", True, {"/joint_states": sorted(arm + grip, key=lambda x: x[0])}, store)
    with pytest.raises(InputError, match="2 different joint sets"):
        read_input(bag)
    with pytest.raises(InputError, match="2 different joint sets"):
        read_input(bag, robot="panda")  # both sets are joints of the panda model
    mp = tmp_path / "map.yaml"
    mp.write_text("joints: [" + ", ".join(ARM) + "]\n")
    (log,) = read_input(bag, map_path=mp)
    np.testing.assert_array_equal(log.q, q)
    assert any(f"{len(stamps)} messages of other joint sets skipped" in n for n in log.notes)
    # a message holding only part of the chosen joints is refused, not padded
    part = arm[:10] + [(arm[10][0], JS, joint_state(store, True, int(stamps[10]), ARM[:6], q[10, :6], dq[10, :6],
                                                    tau[10, :6]))] + arm[11:]
    bag2 = write_bag(tmp_path / "partial.bag", True, {"/joint_states": part}, store)
    with pytest.raises(InputError, match="without \\['panda_joint7'\\]"):
        read_input(bag2, map_path=mp)
    nameless = [(r, JS, joint_state(store, True, r, [], [], [], [])) for r, _, _ in arm]
    bag3 = write_bag(tmp_path / "nameless.bag", True, {"/joint_states": nameless}, store)
    with pytest.raises(InputError, match="name no joints"):
        read_input(bag3)


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_franka_state_bag_measured_torque(tmp_path, ros1):
    store = _store(ros1)
    stamps, q, dq, tau = sample_data()
    tau_d = tau - 3.0
    items = [(int(s), FRANKA, store.types[FRANKA](header=_header(store, ros1, int(s)), q=q[k], dq=dq[k],
                                                  tau_J=tau[k], tau_J_d=tau_d[k], time=0.0))
             for k, s in enumerate(stamps)]
    bag = write_bag(tmp_path / ("f.bag" if ros1 else "f"), ros1,
                    {"/franka_state_controller/franka_states": items}, store)
    (log,) = read_input(bag)
    np.testing.assert_array_equal(log.tau, tau)  # tau_J, the measured torque
    np.testing.assert_array_equal(log.q, q)
    np.testing.assert_array_equal(log.dq, dq)
    assert log.joint_names == ARM
    mp = tmp_path / "m.yaml"
    mp.write_text("tau_source: tau_J_d\n")
    np.testing.assert_array_equal(read_input(bag, map_path=mp)[0].tau, tau_d)


def test_topic_choice_and_stamp_clash(tmp_path):
    store = _store(True)
    stamps, q, dq, tau = sample_data()
    two = {"/a/joint_states": arm_messages(store, True, stamps, q, dq, tau),
           "/b/joint_states": arm_messages(store, True, stamps, q + 1, dq, tau)}
    bag = write_bag(tmp_path / "two.bag", True, two, store)
    with pytest.raises(InputError, match="--topic"):
        read_input(bag)
    np.testing.assert_array_equal(read_input(bag, topic="/b/joint_states")[0].q, q + 1)
    with pytest.raises(InputError, match="not in the bag"):
        read_input(bag, topic="/c")
    clash = arm_messages(store, True, stamps, q, dq, tau)
    clash[7] = (clash[7][0], JS, joint_state(store, True, int(stamps[6]), ARM, q[7], dq[7], tau[7]))
    bag2 = write_bag(tmp_path / "clash.bag", True, {"/joint_states": clash}, store)
    with pytest.raises(InputError, match="share a time stamp"):
        read_input(bag2)
    mp = tmp_path / "m.yaml"
    mp.write_text("stamp: receive\n")
    (log,) = read_input(bag2, map_path=mp)  # the recorder's clock tells them apart
    np.testing.assert_allclose(log.t, (stamps - stamps[0]) * 1e-9, atol=1e-15)


def _digest(path: Path) -> str:
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    return hashlib.sha256(b"".join(p.read_bytes() for p in files)).hexdigest()


def test_cli_bag_and_bad_bags(tmp_path):
    store = _store(False)
    stamps, q, dq, tau = sample_data()
    bag = write_bag(tmp_path / "run", False, {"/joint_states": arm_messages(store, False, stamps, q, dq, tau)}, store)
    before = _digest(bag)
    res = runner.invoke(app, ["convert", str(bag), "--out", str(tmp_path / "o.parquet"), "--robot", "panda"])
    assert res.exit_code == 0, res.output
    assert "40 rows, 7 joints" in res.output
    assert json.loads(pq.read_schema(tmp_path / "o.parquet").metadata[b"joint_names"]) == ARM
    res = runner.invoke(app, ["convert", str(bag), "--out", str(tmp_path / "o.parquet")])
    assert res.exit_code == 2 and "--force" in res.output  # refuses to overwrite
    res = runner.invoke(app, ["convert", str(bag), "--out", str(bag / "inside.parquet")])
    assert res.exit_code == 2 and "inside the input" in res.output
    assert _digest(bag) == before
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag at all\n" * 10)
    res = runner.invoke(app, ["convert", str(junk), "--out", str(tmp_path / "j.parquet")])
    assert res.exit_code == 2
    assert res.output.count("error:") == 1 and "cannot read as a ROS 1 bag" in res.output and str(junk) in res.output
    assert not (tmp_path / "j.parquet").exists() and junk.read_bytes() == b"not a bag at all\n" * 10


def _utc_of_ns(ns: int) -> datetime:
    """The reference: the stamp as pandas reads Unix ns, to the microsecond a datetime holds."""
    return pd.Timestamp(int(ns), unit="ns", tz="UTC").floor("us").to_pydatetime()


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_start_time_from_the_first_stamp(tmp_path, ros1):
    from mmgp.fleet.work import log_time

    store = _store(ros1)
    stamps, q, dq, tau = sample_data(seed=2)
    items = arm_messages(store, ros1, stamps, q, dq, tau)
    items[0], items[1] = items[1], items[0]  # the earliest stamp recorded second: still the start
    bag = write_bag(tmp_path / ("run.bag" if ros1 else "run"), ros1, {"/joint_states": items}, store)
    (out,) = convert(bag, tmp_path / "log.parquet")
    start = pq.read_schema(out).metadata[b"start_time"].decode()
    assert start.endswith("+00:00") and datetime.fromisoformat(start) == _utc_of_ns(stamps.min())
    assert log_time(out) == (_utc_of_ns(stamps.min()).timestamp(), "start_time")  # what the fleet reads
    franka = [(int(s), FRANKA, store.types[FRANKA](header=_header(store, ros1, int(s)), q=q[k], dq=dq[k],
                                                   tau_J=tau[k], tau_J_d=tau[k], time=0.0))
              for k, s in enumerate(stamps)]
    fbag = write_bag(tmp_path / ("f.bag" if ros1 else "f"), ros1, {"/franka_states": franka}, store)
    (log,) = read_input(fbag)
    assert datetime.fromisoformat(log.metadata["start_time"]) == _utc_of_ns(stamps.min())


def test_no_start_time_from_simulated_time(tmp_path):
    store = _store(False)
    _, q, dq, tau = sample_data()
    sim = 5_000_000_000 + np.arange(len(q), dtype=np.int64) * 10_000_000  # a simulator's clock, from 0
    bag = write_bag(tmp_path / "sim", False, {"/joint_states": arm_messages(store, False, sim, q, dq, tau)}, store)
    (out,) = convert(bag, tmp_path / "log.parquet")
    assert b"start_time" not in pq.read_schema(out).metadata
