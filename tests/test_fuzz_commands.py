"""Fuzzing the inputs of ``mmgp compare`` (log, URDF, options), ``mmgp fleet`` (folders and
lists of logs) and ``mmgp convert`` (mapped CSV + map YAML, UR RTDE CSV, bags that are not bags)
(issue 13).

Each starts from valid inputs and corrupts them (text lines and cells, bytes, YAML values, folder
contents). The invariant, as for the readers (tests/fuzz_strategies.py): one clean InputError on
one line naming the file at fault, or a correct result; never a traceback; no input changed and,
after an error, no output left. ``compare`` goes through the command line (its inputs are read
there); ``fleet`` and ``convert`` through the functions the commands call (``Fleet.fit``,
``read_input`` + ``write_logs``). Size: ``MMGP_FUZZ_SCALE`` multiplies the examples.
"""
from __future__ import annotations

import csv
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import event, given
from hypothesis import strategies as st
from typer.testing import CliRunner

from fuzz_strategies import (assert_clean, digests, fuzz_settings, mutated_bytes, mutated_json, mutated_lines,
                             nasty_values)
from mmgp.cli import app
from mmgp.convert import read_input, write_logs
from mmgp.data.logs import read_log
from mmgp.errors import InputError
from mmgp.fleet import Fleet

ROOT = Path(__file__).resolve().parents[1]
REPLICA = ROOT / "mmgp/resources/replica"
runner = CliRunner()


def _csv_rows(path: Path) -> int:
    """Data rows of a CSV by Python's csv module (an independent count): non-blank rows after the header."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(fh) if any(c.strip() for c in r)]
    except (UnicodeDecodeError, csv.Error, OSError):
        return 10 ** 9
    return max(len(rows) - 1, 0)


# ---------------------------------------------------------------------------------------------
# mmgp compare: the log, the URDF, the options
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def compare_inputs(tmp_path_factory):
    """The replica recording (every 2nd row: 165 samples) as CSV and Parquet, and its URDF."""
    d = tmp_path_factory.mktemp("compare")
    frame = pd.read_parquet(REPLICA / "replica_log.parquet").iloc[::2].reset_index(drop=True)
    frame.to_csv(d / "log.csv", index=False)
    frame.to_parquet(d / "log.parquet", index=False)
    shutil.copy(REPLICA / "replica_lever.urdf", d / "lever.urdf")
    return d


def clean_compare(log: Path, urdf: Path, out: Path, *options: str) -> None:
    """``mmgp compare LOG --urdf URDF --out OUT``: exit 0 with every output written and finite
    figures for the URDF's one joint, or exit 2 with one error line naming the log or the URDF
    (an option's value: an error line, or Click's usage message) and no output; inputs unchanged."""
    before = digests([log, urdf])
    res = runner.invoke(app, ["compare", str(log), "--urdf", str(urdf), "--out", str(out), "--quiet",
                              "--max-train", "60", *options])
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert digests([log, urdf]) == before, "compare changed its input"
    if res.exit_code == 0:
        result = json.loads((out / "compare.json").read_text())
        assert (out / "compare.png").is_file() and (out / "report.html").is_file()
        assert result["joint_names"] == ["lever_joint"]
        assert 2 <= result["n_samples"] <= (_csv_rows(log) if log.suffix == ".csv" else 165)
        for method in result["methods"]:
            nmse = np.asarray(result["nmse"][method], dtype=float)
            assert nmse.shape == (1,) and np.all(np.isfinite(nmse)) and np.all(nmse >= 0)
        event("compared")
        return
    assert res.exit_code == 2, res.output
    assert not out.exists()
    if "Invalid value" in res.stderr or "Usage:" in res.stderr:  # Click refused an option's value
        event("usage error")
        return
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    named = [p for p in (log, urdf) if lines[0].startswith(f"error: file {p}")]
    assert named or options, lines[0]  # only an option's error may name no file
    event("error naming " + (named[0].suffix if named else "no file"))


@fuzz_settings(14)
@given(suffix=st.sampled_from([".csv", ".csv", ".parquet"]), data=st.data())
def test_compare_log_corruptions(compare_inputs, tmp_path_factory, suffix, data):
    d = tmp_path_factory.mktemp("c")
    log = d / f"log{suffix}"
    valid = (compare_inputs / f"log{suffix}").read_bytes()
    if suffix == ".csv" and data.draw(st.booleans()):
        log.write_text(data.draw(mutated_lines(valid.decode())))
    else:
        log.write_bytes(data.draw(mutated_bytes(valid)))
    clean_compare(log, compare_inputs / "lever.urdf", d / "out")


@fuzz_settings(12)
@given(data=st.data())
def test_compare_urdf_corruptions(compare_inputs, tmp_path_factory, data):
    d = tmp_path_factory.mktemp("c")
    urdf = d / "lever.urdf"
    valid = (compare_inputs / "lever.urdf").read_text()
    if data.draw(st.booleans()):
        urdf.write_text(data.draw(mutated_lines(valid, sep=" ")))
    else:
        urdf.write_bytes(data.draw(mutated_bytes(valid.encode())))
    clean_compare(compare_inputs / "log.parquet", urdf, d / "out")


@fuzz_settings(6)
@given(max_train=st.one_of(st.integers(-3, 3), st.sampled_from(["1e3", "many", "", "10000000"])),
       device=st.sampled_from(["cpu", "cuda:7", "gpu", "", "mps", "cpu:0", "meta", "xpu", "auto"]))
def test_compare_option_values(compare_inputs, tmp_path_factory, max_train, device):
    out = tmp_path_factory.mktemp("c") / "out"
    clean_compare(compare_inputs / "log.parquet", compare_inputs / "lever.urdf", out,
                  "--max-train", str(max_train), "--device", device)


# ---------------------------------------------------------------------------------------------
# mmgp fleet: folders and lists of logs
# ---------------------------------------------------------------------------------------------

FAST = {"gp": False}  # the fleet's GP stage does not change what is checked here; it costs seconds


@pytest.fixture(scope="module")
def fleet_inputs(tmp_path_factory):
    """A short replica log as Parquet (naming its URDF in the metadata) and CSV, a labels file."""
    from mmgp.data.outputs import write_table

    d = tmp_path_factory.mktemp("fleet_src")
    shutil.copy(REPLICA / "replica_lever.urdf", d / "lever.urdf")
    frame = pd.read_parquet(REPLICA / "replica_log.parquet")
    write_table(d / "log.parquet", frame, metadata={"urdf": "lever.urdf"})
    frame.to_csv(d / "log.csv", index=False)
    write_table(d / "run_labels.parquet", pd.DataFrame({"t": [0.0], "disturbed": [0]}))
    return d


def _fleet_entry(draw, src: Path, folder: Path, i: int) -> None:
    kind = draw(st.sampled_from(["valid", "parquet bytes", "csv lines", "labels", "other suffix", "empty csv",
                                 "subfolder", "no torque"]))
    if kind == "valid":
        shutil.copy(src / "log.parquet", folder / f"v{i}.parquet")
    elif kind == "parquet bytes":
        (folder / f"p{i}.parquet").write_bytes(draw(mutated_bytes((src / "log.parquet").read_bytes())))
    elif kind == "csv lines":
        (folder / f"c{i}.csv").write_text(draw(mutated_lines((src / "log.csv").read_text())))
    elif kind == "labels":
        shutil.copy(src / "run_labels.parquet", folder / f"r{i}_labels.parquet")
    elif kind == "other suffix":
        (folder / f"notes{i}.txt").write_text("t,q_0,tau_0\n")
    elif kind == "empty csv":
        (folder / f"e{i}.csv").write_bytes(b"")
    elif kind == "subfolder":
        shutil.copytree(src, folder / f"sub{i}", ignore=shutil.ignore_patterns("*.urdf"))
    else:
        pd.DataFrame({"t": np.arange(40) * 0.01, "q_0": np.zeros(40)}).to_csv(folder / f"n{i}.csv", index=False)


def expected_logs(items: list[Path]) -> list[Path]:
    """The logs a list of items names, enumerated here: files as given, folders' top-level
    .parquet/.pq/.csv files that are not labels, in sorted order, first occurrence kept."""
    out = []
    for item in items:
        found = [item] if not item.is_dir() else sorted(
            p for p in item.iterdir() if p.is_file() and p.suffix.lower() in (".parquet", ".pq", ".csv")
            and not p.stem.lower().endswith("labels"))
        out += [p for p in found if p.resolve() not in {q.resolve() for q in out}]
    return out


@fuzz_settings(8)
@given(data=st.data())
def test_fleet_folders_and_lists(fleet_inputs, tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("fleet")
    for i in range(data.draw(st.integers(0, 3))):
        _fleet_entry(data.draw, fleet_inputs, folder, i)
    files = sorted(p for p in folder.iterdir() if p.is_file())
    items = data.draw(st.lists(st.sampled_from([folder, folder / "missing.csv", *files]), min_size=1, max_size=3))
    before = digests([folder])
    try:
        fleet = Fleet(urdf=fleet_inputs / "lever.urdf", engine="serial", diagnosis_settings=FAST).fit(items)
    except InputError as err:
        # only a folder without logs is refused as a whole; a bad log is a row of the table
        assert "\n" not in str(err) and err.file in {str(p) for p in items}, str(err)
        assert Path(err.file).is_dir() and not expected_logs([Path(err.file)]), str(err)
        event("InputError: " + err.message[:25])
    else:
        assert fleet.logs_ == expected_logs(items)
        assert [o["log"] for o in fleet.outcomes_] == [str(p) for p in fleet.logs_]
        for o in fleet.outcomes_:
            if o["error"] is None:
                assert isinstance(o["findings"], list) and o["diagnosis"] is not None
                event("log diagnosed")
            else:  # a bad log is a row with its one-line message naming it, not a traceback
                assert "traceback" not in o and "\n" not in o["error"] and o["log"] in o["error"], o["error"]
                event("log refused")
        assert set(fleet.table_["log"]) == {o["log"] for o in fleet.outcomes_}
    assert digests([folder]) == before, "the fleet changed its input"


# ---------------------------------------------------------------------------------------------
# mmgp convert: mapped CSV + map, RTDE CSV, bags that are not bags
# ---------------------------------------------------------------------------------------------

MAP = {"delimiter": ";", "decimal": ",", "columns": {"t": "zeit_ms", "q": ["w1", "w2"], "dq": ["v1", "v2"],
                                                    "tau": ["m1", "m2"]},
       "units": {"t": "ms", "q": "deg", "dq": "deg/s"}, "joint_names": ["a1", "a2"]}


def _mapped_csv(T: int = 20) -> str:
    rng = np.random.default_rng(5)
    rows = np.hstack([np.arange(T)[:, None] * 4.0, rng.uniform(-90, 90, (T, 2)), rng.normal(size=(T, 2)) * 30,
                      rng.normal(size=(T, 2)), np.zeros((T, 1))])
    lines = ["zeit_ms;w1;w2;v1;v2;m1;m2;status"] + [";".join(f"{v:.6f}".replace(".", ",") for v in r) for r in rows]
    return "\n".join(lines) + "\n"


def _rtde_csv(T: int = 20) -> str:
    rng = np.random.default_rng(0)
    header = ["timestamp"] + [f"{k}_{j}" for k in ("actual_q", "actual_qd", "actual_current_as_torque")
                              for j in range(6)]
    rows = np.hstack([1234.5 + 0.002 * np.arange(T)[:, None], rng.normal(size=(T, 18))])
    return "\n".join([" ".join(header)] + [" ".join(repr(float(v)) for v in r) for r in rows]) + "\n"


def clean_convert(path: Path, map_path: Path | None, out: Path) -> None:
    """``read_input`` + ``write_logs`` (what ``mmgp convert`` runs): an InputError naming the input
    or the map and nothing written, or logs that meet the contract and read back as converted."""
    def convert(p):
        parts = read_input(p, map_path=map_path)
        return parts, write_logs(parts, out, source=p)

    also = () if map_path is None else (map_path,)
    result = assert_clean(convert, path, also=also)
    if result is None:
        assert not out.exists()
        return
    parts, written = result
    (log,) = [read_log(w) for w in written if w.suffix != ".urdf"]
    (part,) = parts
    assert np.all(np.diff(log.t) > 0) and np.all(np.isfinite(log.q)) and np.all(np.isfinite(log.tau))
    for name in ("t", "q", "dq", "tau"):
        if getattr(part, name) is not None:
            np.testing.assert_array_equal(getattr(log, name), getattr(part, name))
    assert path.is_dir() or log.n_samples <= _csv_rows(path)


@fuzz_settings(40)
@given(what=st.sampled_from(["csv lines", "csv bytes", "map values", "map lines"]), data=st.data())
def test_convert_mapped_csv_and_map(tmp_path_factory, what, data):
    d = tmp_path_factory.mktemp("m")
    path, map_path = d / "export.csv", d / "map.yaml"
    text, mapping = _mapped_csv(), MAP
    if what == "csv lines":
        text = data.draw(mutated_lines(text, sep=";"))
    path.write_bytes(data.draw(mutated_bytes(text.encode())) if what == "csv bytes" else text.encode())
    if what == "map values":
        mapping = data.draw(mutated_json(MAP))
    map_text = yaml.safe_dump(mapping)
    map_path.write_text(data.draw(mutated_lines(map_text, sep=":")) if what == "map lines" else map_text)
    clean_convert(path, map_path, d / "out.parquet")


@fuzz_settings(25)
@given(data=st.data())
def test_convert_rtde_csv(tmp_path_factory, data):
    d = tmp_path_factory.mktemp("r")
    path = d / "record.csv"
    text = _rtde_csv()
    path.write_text(data.draw(st.one_of(mutated_lines(text, sep=" "), mutated_lines(text.replace(" ", ","))))
                    if data.draw(st.booleans()) else text)
    if data.draw(st.booleans()):
        path.write_bytes(data.draw(mutated_bytes(path.read_bytes())))
    clean_convert(path, None, d / "out.parquet")


ROS2_METADATA = {"rosbag2_bagfile_information": {
    "version": 9, "storage_identifier": "sqlite3", "duration": {"nanoseconds": 1000},
    "starting_time": {"nanoseconds_since_epoch": 1700000000000000000}, "message_count": 1,
    "topics_with_message_count": [{"topic_metadata": {"name": "/joint_states", "type": "sensor_msgs/msg/JointState",
                                                      "serialization_format": "cdr", "offered_qos_profiles": ""},
                                   "message_count": 1}],
    "compression_format": "", "compression_mode": "", "relative_file_paths": ["run_0.db3"],
    "files": [{"path": "run_0.db3", "starting_time": {"nanoseconds_since_epoch": 1700000000000000000},
               "duration": {"nanoseconds": 1000}, "message_count": 1}], "custom_data": None, "ros_distro": "humble"}}


@fuzz_settings(25)
@given(data=st.data())
def test_convert_a_bag_that_is_not_a_bag(tmp_path_factory, data):
    """A ROS 2 bag folder (metadata.yaml) whose metadata is damaged and whose storage file is
    missing or junk, or a .bag / .db3 / .mcap file of junk bytes."""
    d = tmp_path_factory.mktemp("b")
    if data.draw(st.booleans()):
        path = d / "run"
        path.mkdir()
        meta = data.draw(st.one_of(st.just(ROS2_METADATA), mutated_json(ROS2_METADATA)))
        text = yaml.safe_dump(meta)
        (path / "metadata.yaml").write_text(data.draw(mutated_lines(text, sep=":")) if data.draw(st.booleans())
                                            else text)
        storage = data.draw(st.sampled_from(["none", "empty", "junk", "text"]))
        if storage != "none":
            (path / "run_0.db3").write_bytes({"empty": b"", "junk": data.draw(st.binary(max_size=300)),
                                              "text": b"SQLite format 3\x00" + bytes(200)}[storage])
    else:
        path = d / f"run{data.draw(st.sampled_from(['.bag', '.db3', '.mcap']))}"
        path.write_bytes(data.draw(st.one_of(st.binary(max_size=300), st.sampled_from(
            [b"#ROSBAG V2.0\n" + bytes(64), b"\x89MCAP0\r\n" + bytes(64), b"SQLite format 3\x00" + bytes(100)]))))
    clean_convert(path, None, d / "out.parquet")
    event("read" if (d / "out.parquet").exists() else "refused")


@pytest.fixture(scope="module")
def ros2_bag(tmp_path_factory):
    """A real ROS 2 bag (SQLite storage) of 12 joint-state messages of 2 joints, and its arrays."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    JointState, Header, Time = (store.types[k] for k in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header",
                                                         "builtin_interfaces/msg/Time"))
    rng = np.random.default_rng(3)
    q, tau = rng.normal(size=(12, 2)), rng.normal(size=(12, 2))
    path = tmp_path_factory.mktemp("bag") / "run"
    with Writer(path, version=9) as w:
        conn = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        for k in range(12):
            ns = 1_700_000_000_000_000_000 + k * 10_000_000
            msg = JointState(header=Header(stamp=Time(sec=ns // 10 ** 9, nanosec=ns % 10 ** 9), frame_id=""),
                             name=["a", "b"], position=q[k], velocity=np.zeros(2), effort=tau[k])
            w.write(conn, ns, store.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
    return path, q, tau


@fuzz_settings(20)
@given(which=st.sampled_from(["storage bytes", "storage bytes", "metadata lines", "metadata values"]),
       data=st.data())
def test_convert_a_damaged_ros2_bag(ros2_bag, tmp_path_factory, which, data):
    valid, q, tau = ros2_bag
    path = Path(shutil.copytree(valid, tmp_path_factory.mktemp("b") / "run"))
    (db,) = path.glob("*.db3")
    meta = path / "metadata.yaml"
    if which == "storage bytes":
        db.write_bytes(data.draw(mutated_bytes(db.read_bytes())))
    elif which == "metadata lines":
        meta.write_text(data.draw(mutated_lines(meta.read_text(), sep=":")))
    else:
        meta.write_text(yaml.safe_dump(data.draw(mutated_json(yaml.safe_load(meta.read_text())))))
    out = path.parent / "out.parquet"
    clean_convert(path, None, out)
    if out.exists() and which != "storage bytes":  # what the bag still yields is what was written
        log = read_log(out)
        rows = [int(np.flatnonzero(np.all(q == row, axis=1))[0]) for row in log.q]
        np.testing.assert_array_equal(log.tau, tau[rows])


@pytest.mark.parametrize("damage", ["duration as text", "message count null"])
def test_bag_metadata_that_rosbags_fails_on_with_a_type_error(ros2_bag, tmp_path, damage):
    """Two damages found by the fuzz above: rosbags raised TypeError at open (a duration that is
    text) and when listing the topics (a topic's message count null); both are one InputError."""
    path = Path(shutil.copytree(ros2_bag[0], tmp_path / "run"))
    meta = yaml.safe_load((path / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    if damage == "duration as text":
        info["duration"]["nanoseconds"] = "long"
    else:
        info["topics_with_message_count"][0]["message_count"] = None
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta))
    before = digests([path])
    with pytest.raises(InputError, match="cannot (read as a ROS 2 bag|list the bag's topics)") as err:
        read_input(path)
    assert err.value.file == str(path) and digests([path]) == before


@fuzz_settings(15)
@given(value=nasty_values(), key=st.sampled_from(sorted(MAP) + ["robot", "topic", "stamp", "tau_source", "format",
                                                                  "header", "joints", "current_to_torque"]))
def test_convert_map_keys_of_any_type(tmp_path_factory, value, key):
    d = tmp_path_factory.mktemp("k")
    path, map_path = d / "export.csv", d / "map.yaml"
    path.write_text(_mapped_csv())
    map_path.write_text(json.dumps({**MAP, key: value}))
    clean_convert(path, map_path, d / "out.parquet")


def test_the_valid_inputs_convert(tmp_path):
    """The unmutated inputs of the convert fuzz tests convert, to the values written (so the fuzz
    starts from inputs that work)."""
    (tmp_path / "export.csv").write_text(_mapped_csv())
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(MAP))
    (log,) = read_input(tmp_path / "export.csv", map_path=tmp_path / "map.yaml")
    table = pd.read_csv(io.StringIO(_mapped_csv()), sep=";", decimal=",")
    np.testing.assert_allclose(log.t, table["zeit_ms"] / 1000.0, rtol=1e-12)
    np.testing.assert_allclose(log.q, np.deg2rad(table[["w1", "w2"]].to_numpy()), rtol=1e-12)
    (tmp_path / "record.csv").write_text(_rtde_csv())
    (rtde,) = read_input(tmp_path / "record.csv")
    table = pd.read_csv(io.StringIO(_rtde_csv()), sep=" ")
    np.testing.assert_array_equal(rtde.q, table[[f"actual_q_{j}" for j in range(6)]].to_numpy())
