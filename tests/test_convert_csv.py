"""CSV inputs written here (UR RTDE, franka_ros and JointState exports, a mapped CSV with degrees,
milliseconds, semicolons and decimal commas), converted and compared with what was written; the
refusals go through the command line (one error line, exit 2, input untouched, no output)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.convert import convert, read_input
from mmgp.data.logs import read_log
from mmgp.errors import InputError

runner = CliRunner()
UR = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]


def write_table(path: Path, header: list[str], rows: np.ndarray, sep: str = ",", fmt=repr) -> Path:
    lines = [sep.join(header)] + [sep.join(fmt(float(v)) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def rtde_file(path: Path, fields: dict[str, np.ndarray], t: np.ndarray, sep=" ") -> Path:
    header, cols = ["timestamp"], [t[:, None]]
    for name, arr in fields.items():
        header += [f"{name}_{j}" for j in range(arr.shape[1])]
        cols.append(arr)
    return write_table(path, header, np.hstack(cols), sep)


def rtde_data(T=60, seed=0):
    rng = np.random.default_rng(seed)
    t = 1234.5 + 0.002 * np.arange(T)  # 500 Hz, seconds since the controller started
    return t, {k: rng.normal(size=(T, 6)) for k in ("target_q", "actual_q", "actual_qd", "actual_current",
                                                   "target_moment", "actual_current_as_torque")}


def test_rtde_measured_torque_first(tmp_path):
    t, f = rtde_data()
    path = rtde_file(tmp_path / "rec.csv", f, t)  # UR record.py: space separated
    (log,) = read_input(path)
    np.testing.assert_array_equal(log.t, t)
    np.testing.assert_array_equal(log.q, f["actual_q"])  # not target_q
    np.testing.assert_array_equal(log.dq, f["actual_qd"])
    np.testing.assert_array_equal(log.tau, f["actual_current_as_torque"])
    assert log.joint_names == UR
    mp = tmp_path / "m.yaml"
    mp.write_text("tau_source: target_moment\n")
    np.testing.assert_array_equal(read_input(path, map_path=mp)[0].tau, f["target_moment"])


def test_rtde_currents_need_constants(tmp_path):
    t, f = rtde_data()
    del f["actual_current_as_torque"]
    path = rtde_file(tmp_path / "rec.csv", f, t, sep=",")  # ur_rtde's recorder: commas
    (log,) = read_input(path)  # no constants: the controller's model torque, and a note saying so
    np.testing.assert_array_equal(log.tau, f["target_moment"])
    assert any("not a measurement" in n for n in log.notes)
    k = [13.0, 13.0, 9.5, 4.1, 4.1, 4.1]
    mp = tmp_path / "m.yaml"
    mp.write_text(f"current_to_torque: {k}\n")
    np.testing.assert_allclose(read_input(path, map_path=mp)[0].tau, f["actual_current"] * np.array(k), rtol=1e-15)
    del f["target_moment"]
    only = rtde_file(tmp_path / "cur.csv", f, t)
    with pytest.raises(InputError, match="current_to_torque"):
        read_input(only)
    mp.write_text("current_to_torque: [1, 2]\n")
    with pytest.raises(InputError, match="list of 6 numbers"):
        read_input(only, map_path=mp)


def test_franka_rostopic_csv(tmp_path):
    rng = np.random.default_rng(3)
    T = 30
    stamp = 1_700_000_000_000_000_000 + np.arange(T, dtype=np.int64) * 1_000_003  # ~1 kHz, ns
    q, qd_des, dq, tau, tau_d = (rng.normal(size=(T, 7)) for _ in range(5))
    header = ["%time", "field.header.seq", "field.header.stamp", "field.header.frame_id"]
    header += [f"field.{f}{j}" for f in ("q", "q_d", "dq", "tau_J", "tau_J_d") for j in range(7)] + ["field.time"]
    lines = [",".join(header)]
    for k in range(T):
        vals = np.concatenate([q[k], qd_des[k], dq[k], tau[k], tau_d[k]])
        lines.append(",".join([str(stamp[k] + 77), str(k), str(stamp[k]), ""] + [repr(float(v)) for v in vals] + ["0.5"]))
    path = tmp_path / "franka_states.csv"
    path.write_text("\n".join(lines) + "\n")
    (log,) = read_input(path, robot="panda")
    np.testing.assert_array_equal(log.q, q)
    np.testing.assert_array_equal(log.dq, dq)
    np.testing.assert_array_equal(log.tau, tau)  # tau_J, not tau_J_d
    np.testing.assert_allclose(log.t, (stamp - stamp[0]) * 1e-9, rtol=0, atol=1e-15)
    assert log.joint_names == [f"panda_joint{i}" for i in range(1, 8)] and log.robot == "panda"


def test_joint_states_rostopic_csv(tmp_path):
    rng = np.random.default_rng(4)
    names = ["j_b", "j_a"]
    T = 20
    pos, vel, eff = (rng.normal(size=(T, 2)) for _ in range(3))
    header = ["%time", "field.header.seq", "field.header.stamp", "field.header.frame_id", "field.name0",
              "field.name1", "field.position0", "field.position1", "field.velocity0", "field.velocity1",
              "field.effort0", "field.effort1"]
    rows = [",".join([str(10**18 + k * 10**7), str(k), str(10**18 + k * 10**7), "", *names]
                     + [repr(float(v)) for v in np.concatenate([pos[k], vel[k], eff[k]])]) for k in range(T)]
    path = tmp_path / "js.csv"
    path.write_text("\n".join([",".join(header)] + rows) + "\n")
    mp = tmp_path / "m.yaml"
    mp.write_text("joints: [j_a, j_b]\n")
    (log,) = read_input(path, map_path=mp)
    np.testing.assert_array_equal(log.q, pos[:, ::-1])
    np.testing.assert_array_equal(log.tau, eff[:, ::-1])
    np.testing.assert_allclose(log.t, np.arange(T) * 0.01, atol=1e-15)


def test_mapped_csv_degrees_semicolons(tmp_path):
    rng = np.random.default_rng(5)
    T = 25
    t_ms = np.arange(T) * 4.0
    deg, deg_s = rng.uniform(-90, 90, (T, 2)), rng.normal(size=(T, 2)) * 30
    nm = rng.normal(size=(T, 2))
    fmt = lambda v: f"{v:.6f}".replace(".", ",")  # noqa: E731
    path = write_table(tmp_path / "export.csv", ["zeit_ms", "w1", "w2", "v1", "v2", "m1", "m2", "status"],
                       np.hstack([t_ms[:, None], deg, deg_s, nm, np.zeros((T, 1))]), sep=";", fmt=fmt)
    mp = tmp_path / "map.yaml"
    mp.write_text('delimiter: ";"\ndecimal: ","\ncolumns:\n  t: zeit_ms\n  q: [w1, w2]\n  dq: [v1, v2]\n'
                  "  tau: [m1, m2]\nunits:\n  t: ms\n  q: deg\n  dq: deg/s\njoint_names: [a1, a2]\n")
    (out,) = convert(path, tmp_path / "log.parquet", map_path=mp)
    log = read_log(out)
    rounded = lambda a: np.round(a, 6)  # noqa: E731  (the file holds 6 decimals)
    np.testing.assert_allclose(log.t, t_ms / 1000.0, rtol=1e-12)
    np.testing.assert_allclose(log.q, np.deg2rad(rounded(deg)), rtol=1e-12)
    np.testing.assert_allclose(log.dq, np.deg2rad(rounded(deg_s)), rtol=1e-12)
    np.testing.assert_allclose(log.tau, rounded(nm), rtol=1e-12)
    assert log.joint_names == ["a1", "a2"]
    # no header: columns by index
    bare = tmp_path / "bare.txt"
    bare.write_text("\n".join(line for line in path.read_text().splitlines()[1:]) + "\n")
    mp.write_text('delimiter: ";"\ndecimal: ","\nheader: false\ncolumns: {t: 0, q: [1, 2], tau: [5, 6]}\n'
                  "units: {t: ms, q: deg}\n")
    (log2,) = read_input(bare, map_path=mp)
    np.testing.assert_allclose(log2.q, np.deg2rad(rounded(deg)), rtol=1e-12)


def test_time_policy_on_csv(tmp_path):
    rng = np.random.default_rng(6)
    t = np.arange(30) * 0.01
    q, tau = rng.normal(size=(30, 1)), rng.normal(size=(30, 1))
    mp = tmp_path / "m.yaml"
    mp.write_text("columns: {t: t, q: [p], tau: [f]}\n")
    swapped = np.r_[0:10, 11, 10, 12:30]  # two rows logged out of order
    path = write_table(tmp_path / "a.csv", ["t", "p", "f"], np.hstack([t[:, None], q, tau])[swapped])
    (log,) = read_input(path, map_path=mp)
    np.testing.assert_array_equal(log.q, q)
    reset = np.hstack([t[:, None], q, tau])
    reset[15:, 0] -= 1.0  # the clock jumps back by a second
    with pytest.raises(InputError, match="clock reset"):
        read_input(write_table(tmp_path / "b.csv", ["t", "p", "f"], reset), map_path=mp)


def test_cli_bad_inputs_untouched(tmp_path):
    path = tmp_path / "bad.csv"
    text = "t;p;f\n0;1,0;2\n0.1;zwei;3\n" + "".join(f"{0.1 * k:.1f};1;2\n" for k in range(2, 20))
    path.write_text(text)
    mp = tmp_path / "m.yaml"
    mp.write_text('delimiter: ";"\ncolumns: {t: t, q: [p], tau: [f]}\n')
    cases = [(["--map", str(mp)], "column 'p', row 0"),  # '1,0' with decimal '.'
             (["--map", str(tmp_path / "none.yaml")], "map file does not exist"),
             ([], "no reader recognises this input")]
    for extra, message in cases:
        res = runner.invoke(app, ["convert", str(path), "--out", str(tmp_path / "o.parquet"), *extra])
        assert res.exit_code == 2, res.output
        assert res.output.count("error:") == 1 and message in res.output, res.output
        assert not (tmp_path / "o.parquet").exists()
    mp.write_text('delimiter: ";"\ncolums: {t: t}\n')
    res = runner.invoke(app, ["convert", str(path), "--out", str(tmp_path / "o.parquet"), "--map", str(mp)])
    assert res.exit_code == 2 and "unknown map key(s) ['colums']" in res.output
    mp.write_text('robot: 5\ncolumns: {t: t, q: [p], tau: [f]}\n')
    res = runner.invoke(app, ["convert", str(path), "--out", str(tmp_path / "o.parquet"), "--map", str(mp)])
    assert res.exit_code == 2 and "map key 'robot' must be a string" in res.output
    assert path.read_text() == text


def test_start_time_from_absolute_time_columns(tmp_path):
    from datetime import datetime, timezone

    # a JointState export: the first header stamp (Unix ns) is the start
    T, first = 20, 1_764_235_800_000_000_000  # 2025-11-27T09:30:00Z
    header = ["%time", "field.header.stamp", "field.name0", "field.position0", "field.effort0"]
    rows = [",".join([str(first + k * 10**7 + 55), str(first + k * 10**7), "j", repr(0.1 * k), "0.5"])
            for k in range(T)]
    path = tmp_path / "js.csv"
    path.write_text("\n".join([",".join(header)] + rows) + "\n")
    (log,) = read_input(path)
    assert log.metadata["start_time"] == "2025-11-27T09:30:00+00:00"
    # a mapped CSV whose time column is Unix time in ms: start_time from its first sample, t kept
    t_ms = 1_764_235_800_250.0 + 4.0 * np.arange(T)
    csv = write_table(tmp_path / "abs.csv", ["ms", "p", "f"], np.column_stack([t_ms, np.zeros(T), np.ones(T)]))
    mp = tmp_path / "m.yaml"
    mp.write_text("columns: {t: ms, q: [p], tau: [f]}\nunits: {t: ms}\n")
    (out,) = convert(csv, tmp_path / "abs.parquet", map_path=mp)
    log = read_log(out)
    assert datetime.fromisoformat(log.metadata["start_time"]) == datetime(2025, 11, 27, 9, 30, 0, 250000,
                                                                          tzinfo=timezone.utc)
    np.testing.assert_allclose(log.t, t_ms / 1000.0)
    # RTDE's timestamp counts from the controller's start: no wall clock, no start_time
    t, f = rtde_data()
    (log,) = read_input(rtde_file(tmp_path / "rec.csv", f, t))
    assert "start_time" not in log.metadata
