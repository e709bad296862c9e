"""Log and label reading (mmgp.data.logs) against CONTRACT section 1 (outputs: test_outputs.py).

Every bad input must give exactly one InputError that names the file and, where one exists,
the column and the 0-based data row; the input file must be left byte-for-byte unchanged.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from mmgp.errors import InputError
from mmgp.data.logs import read_labels, read_log, read_table_header, write_log


def good_frame(T=30, n=3, dq=False, ddq=False, seed=0):
    rng = np.random.default_rng(seed)
    cols = {"t": 0.01 * np.arange(T)}
    for j in range(n):
        cols[f"q_{j}"] = rng.normal(size=T)
    if dq:
        for j in range(n):
            cols[f"dq_{j}"] = rng.normal(size=T)
    if ddq:
        for j in range(n):
            cols[f"ddq_{j}"] = rng.normal(size=T)
    for j in range(n):
        cols[f"tau_{j}"] = rng.normal(size=T)
    return pd.DataFrame(cols)


def write(df: pd.DataFrame, path: Path, metadata: dict | None = None) -> Path:
    if path.suffix == ".csv":
        df.to_csv(path, index=False)
    else:
        table = pa.Table.from_pandas(df, preserve_index=False)
        if metadata:
            meta = dict(table.schema.metadata or {})
            meta.update({k.encode(): v.encode() for k, v in metadata.items()})
            table = table.replace_schema_metadata(meta)
        pq.write_table(table, path)
    return path


def digest(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None


def expect_error(fn, path: Path, *, column=..., row=..., contains: str | None = None) -> InputError:
    """Call fn, which must raise one InputError naming ``path`` (and column/row when given),
    and must leave ``path`` unchanged."""
    before = digest(path)
    with pytest.raises(InputError) as info:
        fn()
    err = info.value
    assert digest(path) == before, "input file was modified"
    msg = str(err)
    assert err.file == str(path)
    assert str(path) in msg
    if column is not ...:
        assert err.column == column, msg
        if column is not None:
            assert f"'{column}'" in msg
    if row is not ...:
        assert err.row == row, msg
        if row is not None:
            assert f"row {row}" in msg
    if contains is not None:
        assert contains in msg, msg
    return err


@pytest.fixture(params=[".parquet", ".csv"])
def suffix(request):
    return request.param


# ---------------------------------------------------------------------------------------------
# Good input
# ---------------------------------------------------------------------------------------------

def test_good_log_values_and_shapes(tmp_path, suffix):
    df = good_frame(T=25, n=3, dq=True)
    p = write(df, tmp_path / f"log{suffix}")
    before = digest(p)
    log = read_log(p)
    assert digest(p) == before
    assert log.n_joints == 3 and log.n_samples == 25
    np.testing.assert_array_equal(log.t, df["t"].to_numpy())
    np.testing.assert_array_equal(log.q, df[[f"q_{j}" for j in range(3)]].to_numpy())
    np.testing.assert_array_equal(log.dq, df[[f"dq_{j}" for j in range(3)]].to_numpy())
    np.testing.assert_array_equal(log.tau, df[[f"tau_{j}" for j in range(3)]].to_numpy())
    assert log.ddq is None


def test_parquet_metadata_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    T, n = 40, 2
    t = np.cumsum(rng.uniform(0.001, 0.002, T))
    q, dq, tau = rng.normal(size=(T, n)), rng.normal(size=(T, n)), rng.normal(size=(T, n))
    names = ["shoulder joint", "elbow_\u00e9"]
    p = write_log(tmp_path / "sub" / "log.parquet", t, q, tau, dq=dq, robot="panda", urdf="../r.urdf",
                  joint_names=names)
    log = read_log(p)
    assert log.metadata["robot"] == "panda"
    assert log.metadata["urdf"] == "../r.urdf"
    assert log.joint_names == names
    np.testing.assert_array_equal(log.t, t)
    np.testing.assert_array_equal(log.q, q)
    np.testing.assert_array_equal(log.dq, dq)
    np.testing.assert_array_equal(log.tau, tau)
    assert log.ddq is None
    # What pyarrow itself reads back (independent of read_log's parsing).
    meta = pq.read_schema(p).metadata
    assert json.loads(meta[b"joint_names"].decode()) == names
    # No temporary files left beside the output.
    assert sorted(x.name for x in p.parent.iterdir()) == ["log.parquet"]


def test_csv_write_log_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(2)
    T, n = 20, 2
    t = np.sort(rng.uniform(0, 1, T))
    q, tau = rng.normal(size=(T, n)) * 1e-3, rng.normal(size=(T, n)) * 1e3
    log = read_log(write_log(tmp_path / "log.csv", t, q, tau))
    np.testing.assert_array_equal(log.t, t)
    np.testing.assert_array_equal(log.q, q)
    np.testing.assert_array_equal(log.tau, tau)


# ---------------------------------------------------------------------------------------------
# Bad files
# ---------------------------------------------------------------------------------------------

def test_missing_file(tmp_path):
    p = tmp_path / "nope.parquet"
    expect_error(lambda: read_log(p), p, contains="does not exist")
    assert not p.exists()


def test_folder_instead_of_file(tmp_path):
    p = tmp_path / "dir.parquet"
    p.mkdir()
    expect_error(lambda: read_log(p), p)


@pytest.mark.parametrize("content", [b"", b"PAR1 this is not parquet \x00\x01\x02", b"\x89PNG\r\n\x1a\n" * 20])
def test_corrupt_parquet(tmp_path, content):
    p = tmp_path / "bad.parquet"
    p.write_bytes(content)
    expect_error(lambda: read_log(p), p, contains="unreadable")


def test_truncated_parquet(tmp_path):
    p = write(good_frame(), tmp_path / "log.parquet")
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    expect_error(lambda: read_log(p), p, contains="unreadable")


def test_empty_csv(tmp_path):
    p = tmp_path / "empty.csv"
    p.write_bytes(b"")
    expect_error(lambda: read_log(p), p)


def test_unsupported_suffix(tmp_path):
    p = tmp_path / "log.xlsx"
    p.write_bytes(b"whatever")
    expect_error(lambda: read_log(p), p, contains=".xlsx")


# ---------------------------------------------------------------------------------------------
# Bad columns
# ---------------------------------------------------------------------------------------------

def test_missing_t(tmp_path, suffix):
    p = write(good_frame().drop(columns="t"), tmp_path / f"log{suffix}")
    expect_error(lambda: read_log(p), p, column="t", row=None)


@pytest.mark.parametrize("name", ["time", "Time", "timestamp"])
def test_misnamed_t_gets_a_hint(tmp_path, name):
    p = write(good_frame().rename(columns={"t": name}), tmp_path / "log.csv")
    expect_error(lambda: read_log(p), p, column="t", contains=f"found '{name}'")


def test_missing_tau_column(tmp_path, suffix):
    p = write(good_frame(n=3).drop(columns="tau_1"), tmp_path / f"log{suffix}")
    expect_error(lambda: read_log(p), p, column="tau_1", row=None)


def test_no_q_columns(tmp_path):
    df = good_frame(n=2).rename(columns={"q_0": "pos0", "q_1": "pos1"})
    p = write(df, tmp_path / "log.csv")
    expect_error(lambda: read_log(p), p, column="q_0", contains="pos0")


def test_q_gap(tmp_path, suffix):
    # q_0 and q_2 without q_1 (tau_0..tau_2 present): the gap is the error, not the taus.
    p = write(good_frame(n=3).drop(columns="q_1"), tmp_path / f"log{suffix}")
    expect_error(lambda: read_log(p), p, column="q_1", row=None)


def test_tau_beyond_joint_count(tmp_path):
    df = good_frame(n=2)
    df["tau_2"] = 0.0
    p = write(df, tmp_path / "log.csv")
    expect_error(lambda: read_log(p), p, column="tau_2")


@pytest.mark.parametrize("kind", ["dq", "ddq"])
def test_derivatives_for_some_joints_only(tmp_path, suffix, kind):
    df = good_frame(n=3, dq=True, ddq=True).drop(columns=f"{kind}_1")
    p = write(df, tmp_path / f"log{suffix}")
    expect_error(lambda: read_log(p), p, column=f"{kind}_1", row=None)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("column,row", [("q_1", 7), ("tau_0", 0), ("t", 29), ("dq_2", 13)])
def test_non_finite_value(tmp_path, suffix, bad, column, row):
    df = good_frame(T=30, n=3, dq=True)
    df.loc[row, column] = bad
    if column != "t":  # a second bad value later in the same column: the first must be reported
        df.loc[row + 1, column] = bad
    p = write(df, tmp_path / f"log{suffix}")
    expect_error(lambda: read_log(p), p, column=column, row=row)


@pytest.mark.parametrize("text", ["abc", "1.0.0", "--"])
def test_non_numeric_csv_cell(tmp_path, text):
    p = write(good_frame(T=20, n=2), tmp_path / "log.csv")
    lines = p.read_text().splitlines()
    header = lines[0].split(",")
    col = header.index("tau_1")
    row = 11
    cells = lines[1 + row].split(",")
    cells[col] = text
    lines[1 + row] = ",".join(cells)
    p.write_text("\n".join(lines) + "\n")
    expect_error(lambda: read_log(p), p, column="tau_1", row=row)


def test_string_column_in_parquet(tmp_path):
    df = good_frame(T=20, n=2)
    df["q_0"] = df["q_0"].astype(str)
    df.loc[4, "q_0"] = "oops"
    p = write(df, tmp_path / "log.parquet")
    expect_error(lambda: read_log(p), p, column="q_0", row=4)


@pytest.mark.parametrize("row,delta", [(5, 0.0), (17, -0.05), (1, -1.0)])
def test_non_increasing_t(tmp_path, suffix, row, delta):
    df = good_frame(T=30)
    t = df["t"].to_numpy().copy()
    t[row] = t[row - 1] + delta
    df["t"] = t
    p = write(df, tmp_path / f"log{suffix}")
    expect_error(lambda: read_log(p), p, column="t", row=row)


def test_too_few_samples(tmp_path, suffix):
    p = write(good_frame(T=4), tmp_path / f"log{suffix}")
    expect_error(lambda: read_log(p, min_samples=10), p, contains="too few")
    assert read_log(p, min_samples=4).n_samples == 4


def test_header_only_csv(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("t,q_0,tau_0\n")
    expect_error(lambda: read_log(p), p, contains="too few")


@pytest.mark.parametrize("n_log,n_robot,column", [(3, 4, "q_3"), (3, 2, "q_2")])
def test_joint_count_mismatch(tmp_path, suffix, n_log, n_robot, column):
    p = write(good_frame(n=n_log), tmp_path / f"log{suffix}")
    err = expect_error(lambda: read_log(p, n_joints=n_robot), p, column=column)
    assert str(n_log) in str(err) and str(n_robot) in str(err)


def test_metadata_joint_names_length_mismatch(tmp_path):
    p = write(good_frame(n=3), tmp_path / "log.parquet", metadata={"joint_names": json.dumps(["a", "b"])})
    expect_error(lambda: read_log(p), p, contains="joint_names")


def test_metadata_joint_names_not_a_list(tmp_path):
    p = write(good_frame(n=2), tmp_path / "log.parquet", metadata={"joint_names": "a,b"})
    expect_error(lambda: read_log(p), p, contains="joint_names")


# ---------------------------------------------------------------------------------------------
# Labels
# ---------------------------------------------------------------------------------------------

def labels_frame(T=20, seed=0):
    rng = np.random.default_rng(seed)
    return pd.DataFrame({"t": 0.01 * np.arange(T), "disturbed": rng.choice([-1, 0, 1], T),
                         "mode": rng.integers(0, 3, T)})


def test_labels_matched_to_training_times(tmp_path, suffix):
    df = labels_frame()
    shuffled = df.sample(frac=1.0, random_state=3).reset_index(drop=True)
    p = write(shuffled, tmp_path / f"labels{suffix}")
    t_train = df["t"].to_numpy()[::2] + 3e-7  # a subset, with tiny clock round-off
    out = read_labels(p, t=t_train)
    np.testing.assert_array_equal(out["disturbed"].to_numpy(), df["disturbed"].to_numpy()[::2])
    np.testing.assert_array_equal(out["mode"].to_numpy(), df["mode"].to_numpy()[::2])


@pytest.mark.parametrize("value", [2, 0.5, -2])
def test_labels_disturbed_out_of_range(tmp_path, suffix, value):
    df = labels_frame()
    df["disturbed"] = df["disturbed"].astype(float)
    df.loc[9, "disturbed"] = value
    p = write(df, tmp_path / f"labels{suffix}")
    expect_error(lambda: read_labels(p), p, column="disturbed", row=9)


def test_labels_mode_not_integer(tmp_path, suffix):
    df = labels_frame()
    df["mode"] = df["mode"].astype(float)
    df.loc[6, "mode"] = 1.5
    p = write(df, tmp_path / f"labels{suffix}")
    expect_error(lambda: read_labels(p), p, column="mode", row=6)


def test_labels_nan(tmp_path):
    df = labels_frame().astype({"disturbed": float})
    df.loc[3, "disturbed"] = np.nan
    p = write(df, tmp_path / "labels.parquet")
    expect_error(lambda: read_labels(p), p, column="disturbed", row=3)


def test_labels_missing_for_a_training_time(tmp_path, suffix):
    df = labels_frame()
    p = write(df.drop(index=12), tmp_path / f"labels{suffix}")
    err = expect_error(lambda: read_labels(p, t=df["t"].to_numpy()), p, column="t")
    assert "0.120000" in str(err)


def test_labels_without_label_columns(tmp_path):
    p = write(labels_frame()[["t"]], tmp_path / "labels.csv")
    expect_error(lambda: read_labels(p), p)


def test_labels_missing_t(tmp_path):
    p = write(labels_frame().drop(columns="t"), tmp_path / "labels.csv")
    expect_error(lambda: read_labels(p), p, column="t")


# ---------------------------------------------------------------------------------------------
# Issue 13: odd CSV dialects, duplicated columns, clock jumps, encodings
# ---------------------------------------------------------------------------------------------

def european_csv(df: pd.DataFrame, sep: str) -> str:
    """``df`` as a spreadsheet in a European locale writes it: ``sep`` between cells, decimal commas."""
    lines = [sep.join(df.columns)]
    for row in df.itertuples(index=False):
        lines.append(sep.join(repr(float(v)).replace(".", ",") for v in row))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("sep", [";", "\t"])
def test_decimal_comma_csv_is_read_exactly(tmp_path, sep):
    df = good_frame(T=20, n=2, dq=True)
    p = tmp_path / "log.csv"
    p.write_text(european_csv(df, sep))
    before = digest(p)
    log = read_log(p)
    assert digest(p) == before
    np.testing.assert_array_equal(log.t, df["t"].to_numpy())
    np.testing.assert_array_equal(log.q, df[["q_0", "q_1"]].to_numpy())
    np.testing.assert_array_equal(log.dq, df[["dq_0", "dq_1"]].to_numpy())
    np.testing.assert_array_equal(log.tau, df[["tau_0", "tau_1"]].to_numpy())


def test_semicolon_csv_with_decimal_points_is_read(tmp_path):
    df = good_frame(T=15, n=1)
    p = tmp_path / "log.csv"
    df.to_csv(p, sep=";", index=False)
    np.testing.assert_array_equal(read_log(p).tau, df[["tau_0"]].to_numpy())


def test_decimal_point_among_decimal_commas_names_the_cell(tmp_path):
    df = good_frame(T=15, n=1)
    text = european_csv(df, ";").splitlines()
    cells = text[1 + 8].split(";")
    cells[2] = cells[2].replace(",", ".")  # tau_0 of data row 8
    text[1 + 8] = ";".join(cells)
    p = tmp_path / "log.csv"
    p.write_text("\n".join(text) + "\n")
    expect_error(lambda: read_log(p), p, column="tau_0", row=8, contains="decimal commas")


def test_header_mixing_separators(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("t;q_0,tau_0\n" + "0;1,2\n" * 12)
    expect_error(lambda: read_log(p), p, contains="mixes separators ',' and ';'")


def test_space_separated_header(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("t q_0 tau_0\n" + "".join(f"{i} 1 2\n" for i in range(12)))
    expect_error(lambda: read_log(p), p, contains="spaces")


def test_header_cells_with_spaces_after_commas(tmp_path):
    df = good_frame(T=12, n=2)
    p = tmp_path / "log.csv"
    df.to_csv(p, index=False)
    lines = p.read_text().splitlines()
    p.write_text("\n".join([", ".join(lines[0].split(","))] + lines[1:]) + "\n")
    np.testing.assert_array_equal(read_log(p).q, df[["q_0", "q_1"]].to_numpy())


def test_missing_header_line(tmp_path):
    p = tmp_path / "log.csv"
    good_frame(T=12, n=1).to_csv(p, index=False, header=False)
    expect_error(lambda: read_log(p), p, column="t", contains="header line")


def test_missing_t_says_what_the_header_has(tmp_path):
    p = write(good_frame(T=12, n=1).rename(columns={"t": "stamp"}), tmp_path / "log.csv")
    expect_error(lambda: read_log(p), p, column="t", contains="'stamp'")


def test_duplicated_csv_column(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("t,q_0,tau_0,q_0\n" + "".join(f"{0.01 * i},{i},{i},{-i}\n" for i in range(12)))
    expect_error(lambda: read_log(p), p, column="q_0", contains="twice")


def test_duplicated_parquet_column_is_one_line(tmp_path):
    x = pa.array(0.01 * np.arange(12))
    p = tmp_path / "log.parquet"
    pq.write_table(pa.table([x, x, x, x], names=["t", "q_0", "tau_0", "q_0"]), p)
    err = expect_error(lambda: read_log(p), p, column="q_0", contains="twice")
    assert "\n" not in str(err)


def test_duplicated_labels_column(tmp_path):
    p = tmp_path / "labels.csv"
    p.write_text("t,disturbed,disturbed\n" + "".join(f"{0.01 * i},0,1\n" for i in range(12)))
    expect_error(lambda: read_labels(p), p, column="disturbed", contains="twice")


def test_clock_jump_is_refused_at_read_time(tmp_path, suffix):
    df = good_frame(T=30)
    df.loc[17:, "t"] += 1.7e9  # epoch seconds after a controller restart
    p = write(df, tmp_path / f"log{suffix}")
    err = expect_error(lambda: read_log(p), p, column="t", row=17)
    assert "1.7e+09 s" in str(err)


@pytest.mark.parametrize("pause_s", [60.0, 3600.0, 16 * 3600.0, 86_000.0])
def test_pauses_up_to_a_day_are_accepted(tmp_path, pause_s):
    df = good_frame(T=30)
    df.loc[12:, "t"] += pause_s
    p = write(df, tmp_path / "log.parquet")
    np.testing.assert_array_equal(read_log(p).t, df["t"].to_numpy())


def test_epoch_time_stamps_throughout_are_accepted(tmp_path):
    df = good_frame(T=30)
    df["t"] += 1.7e9
    p = write(df, tmp_path / "log.parquet")
    np.testing.assert_array_equal(read_log(p).t, df["t"].to_numpy())


def test_latin1_csv(tmp_path):
    p = tmp_path / "log.csv"
    p.write_bytes(b"t,q_0,tau_0\n" + b"0,1,2\n" * 5 + "# mesur\u00e9\n".encode("latin-1"))
    expect_error(lambda: read_log(p), p, contains="not UTF-8 text (byte 0xE9 on line 7)")


def test_utf16_csv(tmp_path):
    p = tmp_path / "log.csv"
    p.write_bytes(good_frame(T=12, n=1).to_csv(index=False).encode("utf-16"))
    expect_error(lambda: read_log(p), p, contains="UTF-16")


def test_utf8_bom_csv_is_read(tmp_path):
    df = good_frame(T=12, n=1)
    p = tmp_path / "log.csv"
    p.write_bytes(df.to_csv(index=False).encode("utf-8-sig"))
    np.testing.assert_array_equal(read_log(p).t, df["t"].to_numpy())


@pytest.mark.parametrize("content,contains", [
    (bytes(range(256)) * 4, "binary content"),
    (b"\n\n   \n", "empty"),
    (b"PAR1\x00\x00", "Parquet file with a CSV name"),
])
def test_garbage_csv_is_one_line(tmp_path, content, contains):
    p = tmp_path / "log.csv"
    p.write_bytes(content)
    err = expect_error(lambda: read_log(p), p, contains=contains)
    assert "\n" not in str(err)


def test_header_only_labels(tmp_path):
    p = tmp_path / "labels.csv"
    p.write_text("t,disturbed\n")
    expect_error(lambda: read_labels(p, t=np.arange(3.0)), p, contains="header only")


def test_row_with_extra_fields(tmp_path):
    p = write(good_frame(T=12, n=1), tmp_path / "log.csv")
    lines = p.read_text().splitlines()
    lines[1 + 6] += ",9"
    p.write_text("\n".join(lines) + "\n")
    expect_error(lambda: read_log(p), p, row=6, contains="line 8 has 4 fields")


def test_first_row_with_extra_fields(tmp_path):
    # pandas would take the first column as an index (or drop the extra field with a warning)
    p = write(good_frame(T=12, n=1), tmp_path / "log.csv")
    lines = p.read_text().splitlines()
    lines[1] += ",9"
    p.write_text("\n".join(lines) + "\n")
    expect_error(lambda: read_log(p), p, row=0, contains="the first data row has 4 fields but the header has 3")


def test_row_with_missing_field(tmp_path):
    p = write(good_frame(T=12, n=1), tmp_path / "log.csv")
    lines = p.read_text().splitlines()
    lines[1 + 4] = lines[1 + 4].rsplit(",", 1)[0]
    p.write_text("\n".join(lines) + "\n")
    expect_error(lambda: read_log(p), p, column="tau_0", row=4, contains="missing value")


def test_timestamp_typed_time_column(tmp_path):
    df = good_frame(T=12, n=1)
    df["t"] = pd.Timestamp("2024-01-01") + pd.to_timedelta(df["t"], unit="s")
    p = write(df, tmp_path / "log.parquet")
    expect_error(lambda: read_log(p), p, column="t", contains="type")


def test_list_typed_parquet_column(tmp_path):
    df = good_frame(T=12, n=1)
    df["q_0"] = [[v, v] for v in df["q_0"]]
    p = write(df, tmp_path / "log.parquet")
    expect_error(lambda: read_log(p), p, column="q_0", row=0)


def test_labels_mode_too_large_for_an_integer(tmp_path):
    df = labels_frame().astype({"mode": float})
    df.loc[5, "mode"] = 1e300
    p = write(df, tmp_path / "labels.parquet")
    expect_error(lambda: read_labels(p), p, column="mode", row=5)


def test_input_error_is_one_line():
    err = InputError("first line\nsecond line", file="a\nb.csv", column="q_0", row=3)
    assert "\n" not in str(err)
    assert str(err) == "file a; b.csv, column 'q_0', row 3: first line; second line"


def test_read_table_header_reads_as_read_log_does(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text(european_csv(good_frame(T=12, n=2), ";"))
    assert read_table_header(p) == (["t", "q_0", "q_1", "tau_0", "tau_1"], {})
    p = write(good_frame(T=12, n=1), tmp_path / "log.parquet", metadata={"robot": "panda",
                                                                       "joint_names": '["j"]'})
    assert read_table_header(p) == (["t", "q_0", "tau_0"], {"robot": "panda", "joint_names": ["j"]})
    p = tmp_path / "dup.csv"
    p.write_text("t,q_0,q_0\n")
    expect_error(lambda: read_table_header(p), p, column="q_0")


def test_integer_too_large_for_float64(tmp_path):
    # pandas keeps a 400-digit cell as a Python int, and pd.to_numeric then raised OverflowError
    p = write(good_frame(T=12, n=1), tmp_path / "log.csv")
    lines = p.read_text().splitlines()
    cells = lines[1 + 3].split(",")
    cells[1] = "9" * 400
    lines[1 + 3] = ",".join(cells)
    p.write_text("\n".join(lines) + "\n")
    expect_error(lambda: read_log(p), p, column="q_0", row=3, contains="found inf")


@pytest.mark.parametrize("name", ["q_00", "q_\u0660", "q_0\n"])
def test_near_contract_column_names_are_not_joint_columns(tmp_path, name):
    # 'q_00' was taken for joint 0 and then looked up as 'q_0': a KeyError (found by fuzzing)
    df = good_frame(T=12, n=2).rename(columns={"q_0": name})
    p = write(df, tmp_path / "log.parquet")
    expect_error(lambda: read_log(p), p, column="q_0")
