"""mmgp fleet: Ray tasks per log, the aggregated table, drift flags, bad logs, the command.

Logs are a 1-DOF lever written here: torque = Pinocchio's inverse dynamics of the URDF below
plus a planted Coulomb friction tau_c * tanh(dq / 0.02) and noise. The references are the
diagnosis called directly, log by log, and drift series built by hand.
"""
import json
import math
import os
import sys

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.data.logs import read_log
from mmgp.data.outputs import write_table
from mmgp.diagnosis import Diagnoser
from mmgp.fleet import Fleet, expand_logs
from mmgp.fleet.drift import flag_drift
from mmgp.fleet.engine import JOINED_TASK_OPTIONS, RayMissingError, import_ray, ray_session
from mmgp.fleet.table import finding_rows
from mmgp.physics.robot import RobotModel
from mmgp.sim.concealed import ACTUATOR_URDF


URDF = ACTUATOR_URDF  # the 1-DOF lever of mmgp.sim (0.73 kg at 0.2 m), written beside the logs
before_blas = os.environ.get("OPENBLAS_NUM_THREADS")  # set here only while the fleet starts Ray
FAST = {"gp": False}  # the third (GP) stage does not change findings; it costs seconds per log
TIMES = ["2026-01-01T08:00:00Z", "2026-01-02T08:00:00Z", "2026-01-03T08:00:00Z"]
runner = CliRunner()


def lever_frame(robot, seed: int, tau_c: float, n: int = 1200) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0
    w = np.array([0.9, 2.3]) * (1 + 0.1 * rng.standard_normal(2))
    a, ph = np.array([0.8, 0.3]), rng.uniform(0, 2 * np.pi, 2)
    q = (a * np.sin(w * t[:, None] + ph)).sum(1)[:, None]
    dq = (a * w * np.cos(w * t[:, None] + ph)).sum(1)[:, None]
    ddq = (-a * w ** 2 * np.sin(w * t[:, None] + ph)).sum(1)[:, None]
    tau = robot.rnea(q, dq, ddq) + tau_c * np.tanh(dq / 0.02) + 0.01 * rng.standard_normal(q.shape)
    return pd.DataFrame({"t": t, "q_0": q[:, 0], "dq_0": dq[:, 0], "ddq_0": ddq[:, 0], "tau_0": tau[:, 0]})


def write_lever_log(folder, name: str, seed: int, tau_c: float, start_time: str | None = None, n: int = 1200,
                    legacy_time: str | None = None):
    """A lever log; ``start_time`` is the contract's key, ``legacy_time`` the key older fleets read."""
    robot = RobotModel.from_urdf(folder / "lever.urdf")
    meta = {"urdf": "lever.urdf", "joint_names": json.dumps(["lever_joint"])}
    if start_time is not None:
        meta["start_time"] = start_time
    if legacy_time is not None:
        meta["log_time"] = legacy_time
    write_table(folder / name, lever_frame(robot, seed, tau_c, n), metadata=meta)
    return folder / name


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for the module, started as the fleet starts it; the fleets join it."""
    with ray_session(address=None, workers=1) as (session, options):
        yield session, options


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    (d / "lever.urdf").write_text(URDF)
    for i, (tau_c, when) in enumerate(zip([0.2, 0.2, 0.5], TIMES)):
        write_lever_log(d, f"log{i}.parquet", seed=i, tau_c=tau_c, start_time=when)
    # bad input: a log without its torque column (and without a start_time: its mtime orders it)
    write_table(d / "no_torque.parquet", pd.DataFrame({"t": np.arange(300) / 200.0, "q_0": np.zeros(300)}),
                metadata={"urdf": "lever.urdf"})
    write_table(d / "log0_labels.parquet", pd.DataFrame({"t": [0.0], "disturbed": [0]}))  # not a log
    return d


@pytest.fixture(scope="module")
def ray_fleet(local_ray, fleet_dir):
    return Fleet(engine="ray", workers=1, baseline=2, diagnosis_settings=FAST).fit([fleet_dir])


def direct_rows(path) -> list[tuple]:
    """Rows the table must hold for one log, from the diagnosis called here: value, value -+ 2 std."""
    robot = RobotModel.from_urdf(path.parent / "lever.urdf", ["lever_joint"])
    res = Diagnoser(**FAST).fit(read_log(path, n_joints=1, joint_names=["lever_joint"]), robot)
    rows = []
    for f in res.findings_:
        std = f["evidence"]["params_std"]
        for name, v in f["params"].items():
            vals, sds = (v, std[name]) if isinstance(v, list) else ([v], [std[name]])
            for k, (x, s) in enumerate(zip(vals, sds)):
                param = f"{name}[{k}]" if isinstance(v, list) else name
                rows.append((f["effect"], f.get("joint"), param, x, x - 2 * s, x + 2 * s))
    return rows


def test_ray_table_matches_the_diagnosis_called_directly(ray_fleet, fleet_dir):
    table = ray_fleet.table_
    assert sorted(set(table["log"])) == sorted(str(fleet_dir / n) for n in
                                                ("log0.parquet", "log1.parquet", "log2.parquet", "no_torque.parquet"))
    for i in range(3):
        path = fleet_dir / f"log{i}.parquet"
        got = table[table["log"] == str(path)]
        assert (got["log_time"] == pd.Timestamp(TIMES[i])).all() and (got["log_time_source"] == "start_time").all()
        assert (got["robot"] == "lever").all() and got["error"].isna().all()
        expected = direct_rows(path)
        assert expected, "the planted friction must be found"
        assert len(got) == len(expected)
        for effect, joint, param, value, lo, hi in expected:
            row = got[(got["effect"] == effect) & (got["joint"] == joint) & (got["param"] == param)]
            assert len(row) == 1
            np.testing.assert_allclose(row[["value", "lo", "hi"]].to_numpy()[0], [value, lo, hi], rtol=1e-9)
    friction = table[table["param"] == "tau_c"].set_index("log")["value"]
    np.testing.assert_allclose(friction[str(fleet_dir / "log2.parquet")], 0.5, atol=0.01)


def test_bad_log_is_a_row_with_its_message(ray_fleet, fleet_dir):
    bad = ray_fleet.table_[ray_fleet.table_["log"] == str(fleet_dir / "no_torque.parquet")]
    assert len(bad) == 1 and bad["effect"].isna().all()
    msg = bad["error"].iloc[0]
    assert "no_torque.parquet" in msg and "tau_0" in msg
    # no start_time in its metadata: its time is the file's mtime, and the table says so
    assert bad["log_time_source"].iloc[0] == "mtime"
    assert bad["log_time"].iloc[0] == pd.Timestamp(os.stat(fleet_dir / "no_torque.parquet").st_mtime, unit="s", tz="UTC")


def test_drift_flag_end_to_end(ray_fleet, fleet_dir):
    flagged = ray_fleet.table_[ray_fleet.table_["drift"]]
    assert list(flagged["log"]) == [str(fleet_dir / "log2.parquet")]
    (series,) = [s for s in ray_fleet.drift_["series"] if s["param"] == "tau_c"]
    assert series["status"] == "drift" and series["first_log"] == str(fleet_dir / "log2.parquet")
    assert series["direction"] == "up"


def planted(rows):
    """A fleet table from (log index, effect, param, value, half-width) tuples; log i at day i."""
    recs = [{"log": f"L{i}", "robot": "r1", "log_time": pd.Timestamp("2026-03-01", tz="UTC") + pd.Timedelta(days=i),
             "log_time_source": "start_time", "effect": e, "joint": "j1", "param": p, "value": v, "lo": v - h,
             "hi": v + h, "error": None} for i, e, p, v, h in rows]
    return pd.DataFrame(recs).sample(frac=1.0, random_state=0)  # order must not matter


def test_drift_on_a_planted_series():
    base = [(i, "coulomb_friction", "tau_c", v, 0.05) for i, v in enumerate([1.0, 1.02, 0.98, 1.01])]
    # baseline (first 3 logs): [0.93, 1.07]
    later = [(3, "coulomb_friction", "tau_c", 1.01, 0.05),    # inside: steady
             (4, "coulomb_friction", "tau_c", 1.10, 0.05),    # [1.05, 1.15] overlaps 1.07: not yet
             (5, "coulomb_friction", "tau_c", 1.13, 0.05),    # [1.08, 1.18] entirely above: drift
             (6, "coulomb_friction", "tau_c", 0.85, 0.05)]    # [0.80, 0.90] entirely below: drift
    steady = [(i, "viscous_friction", "b", 0.3 + 0.001 * i, 0.01) for i in range(7)]
    new = [(5, "armature", "inertia", 0.02, 0.001)]
    table = planted(base[:3] + later + steady + new)
    out, report = flag_drift(table, baseline=3)
    assert sorted(out.loc[out["drift"], "log"]) == ["L5", "L6"]
    by = {s["effect"]: s for s in report["series"]}
    assert by["coulomb_friction"]["status"] == "drift" and by["coulomb_friction"]["first_log"] == "L5"
    assert by["coulomb_friction"]["baseline"]["lo"] == pytest.approx(0.93)
    assert by["coulomb_friction"]["baseline"]["hi"] == pytest.approx(1.07)
    assert by["viscous_friction"]["status"] == "steady"
    assert by["armature"]["status"] == "appeared" and by["armature"]["first_log"] == "L5"


def test_failed_logs_do_not_count_in_the_baseline():
    rows = [(i, "coulomb_friction", "tau_c", v, 0.01) for i, v in [(1, 1.0), (2, 1.0), (3, 1.5)]]
    table = planted(rows)
    failed = {"log": "L0", "robot": "r1", "log_time": pd.Timestamp("2026-03-01", tz="UTC"), "log_time_source": "mtime",
              "effect": None, "joint": None, "param": None, "value": math.nan, "lo": math.nan, "hi": math.nan,
              "error": "unreadable"}
    out, report = flag_drift(pd.concat([table, pd.DataFrame([failed])], ignore_index=True), baseline=2)
    assert report["baseline_logs"]["r1"] == ["L1", "L2"]
    assert sorted(out.loc[out["drift"], "log"]) == ["L3"]


def test_vector_params_become_components():
    f = {"effect": "payload", "link": "arm", "params": {"link": "arm", "mass": 0.5, "com": [0.1, -0.2, 0.3]},
         "evidence": {"params_std": {"mass": 0.01, "com": [0.001, 0.002, 0.003]}}}
    rows = [(r["joint"], r["param"]) for r in finding_rows(f)]
    assert rows == [("arm", "mass"), ("arm", "com[0]"), ("arm", "com[1]"), ("arm", "com[2]")]
    np.testing.assert_allclose([(r["value"], r["lo"], r["hi"]) for r in finding_rows(f)],
                               [(0.5, 0.48, 0.52), (0.1, 0.098, 0.102), (-0.2, -0.204, -0.196), (0.3, 0.294, 0.306)])
    whole = {"effect": "external_disturbance", "joint": None,
             "params": {"n_samples": 40, "fraction": 0.1, "spans_s": [[1.0, 2.0]]}, "evidence": {}}
    got = [(r["joint"], r["param"], r["value"], math.isnan(r["lo"])) for r in finding_rows(whole)]
    assert got == [(None, "n_samples", 40.0, True), (None, "fraction", 0.1, True)]


def test_tasks_run_single_threaded(local_ray):
    def threads():
        from threadpoolctl import threadpool_info

        from mmgp.threads import limit_threads

        with limit_threads(1):
            import torch

            inside = (torch.get_num_threads(), sorted({p["num_threads"] for p in threadpool_info()}))
        return os.environ.get("OMP_NUM_THREADS"), os.environ.get("OPENBLAS_NUM_THREADS"), inside

    session, options = local_ray
    # the workers of a Ray started here inherit the variables; a joined session gets them per task
    for opts in (options, JOINED_TASK_OPTIONS):
        omp, blas, (torch_threads, pools) = session.get(session.remote(**opts)(threads).remote())
        assert (omp, blas, torch_threads, pools) == ("1", "1", 1, [1])
    assert os.environ.get("OPENBLAS_NUM_THREADS") == before_blas  # this process's own setting is back


def test_command_writes_table_trends_and_errors(local_ray, tmp_path):
    (tmp_path / "lever.urdf").write_text(URDF)
    # the key fleets read before contract 1.2 ('log_time', here without zone) is still read
    good = write_lever_log(tmp_path, "good.parquet", seed=7, tau_c=0.3, legacy_time="2026-02-01T00:00:00", n=800)
    bad = tmp_path / "missing.parquet"
    out = tmp_path / "out"
    res = runner.invoke(app, ["fleet", str(good), str(bad), "--out", str(out), "--workers", "1"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(out / "fleet.parquet")
    assert list(table.columns[:10]) == ["log", "robot", "log_time", "log_time_source", "effect", "joint", "param",
                                        "value", "lo", "hi"]
    assert "drift" in table.columns and "error" in table.columns
    ok = table[table["log"] == str(good)]
    assert ok["log_time"].iloc[0] == pd.Timestamp("2026-02-01T00:00:00", tz="UTC")  # no zone: UTC
    assert ok["log_time_source"].iloc[0] == "log_time"
    assert "coulomb_friction" in set(ok["effect"])
    assert "does not exist" in table.loc[table["log"] == str(bad), "error"].iloc[0]
    assert json.loads((out / "logs" / "good" / "findings.json").read_text())["findings"]
    assert (out / "logs" / "missing" / "error.txt").is_file()
    assert any(p.suffix == ".png" for p in (out / "trends").iterdir())
    drift = json.loads((out / "drift.json").read_text())
    assert drift["baseline_size"] == 5 and {s["status"] for s in drift["series"]} == {"no baseline"}
    again = runner.invoke(app, ["fleet", str(good), "--out", str(out)])
    assert again.exit_code == 2 and "not empty" in again.output


def test_training_in_the_fleet(tmp_path):
    from mmgp import MultimodalGP

    (tmp_path / "lever.urdf").write_text(URDF)
    log = write_lever_log(tmp_path, "a.parquet", seed=3, tau_c=0.2, n=600)
    quick = {"max_sweeps": 2, "min_sweeps": 1, "average_last": 1, "fit_iter": 5, "max_support": 150,
             "final_support": 150, "fit_points": 150}
    fleet = Fleet(engine="serial", train=True, diagnosis_settings=FAST, train_settings=quick).fit([log])
    fleet.write(tmp_path / "out")
    folder = tmp_path / "out" / "logs" / "a" / "train"
    report = json.loads((folder / "report.json").read_text())
    rows = fleet.table_[fleet.table_["effect"] == "training"].set_index("param")["value"]
    assert rows["modes[0].noise_std"] == report["hyperparameters"][0]["per_joint"][0]["noise_std"]
    assert rows["disturbed_fraction"] == report["disturbance"]["n_disturbed"] / report["n_samples"]
    model = MultimodalGP.load(folder)
    frame = pd.read_parquet(log)
    mean, std = model.predict(frame[["q_0"]].to_numpy(), frame[["dq_0"]].to_numpy(), frame[["ddq_0"]].to_numpy())
    assert mean.shape == (600, 1) and np.isfinite(std).all()


def test_folders_skip_label_files_and_repeats(fleet_dir):
    got = expand_logs([fleet_dir, fleet_dir / "log1.parquet"])
    assert [p.name for p in got] == ["log0.parquet", "log1.parquet", "log2.parquet", "no_torque.parquet"]


def test_missing_ray_is_explained(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    with pytest.raises(RayMissingError, match=r"mmgp\[fleet\]"):
        import_ray()
    (tmp_path / "lever.urdf").write_text(URDF)
    log = write_lever_log(tmp_path, "a.parquet", seed=1, tau_c=0.2, n=400)
    res = runner.invoke(app, ["fleet", str(log), "--out", str(tmp_path / "out")])
    assert res.exit_code == 1 and "pip install 'mmgp[fleet]'" in res.output
    assert not (tmp_path / "out").exists()


def test_the_levers_reversals_are_not_pushes(tmp_path):
    """These levers' friction turns over 0.02 rad/s, the diagnosis' smooth sign over ~0.008: the
    misfit through each reversal is no external force. The fit keeps the reversals (a passage is
    not a rest); the push scan leaves them out. Scanned with the fit's mask, two of the three logs
    got a 0.5-0.7 s "push" at a reversal."""
    (tmp_path / "lever.urdf").write_text(URDF)
    robot = RobotModel.from_urdf(tmp_path / "lever.urdf", ["lever_joint"])
    for i, tau_c in enumerate([0.2, 0.2, 0.5]):
        path = write_lever_log(tmp_path, f"log{i}.parquet", seed=i, tau_c=tau_c)
        res = Diagnoser(**FAST).fit(read_log(path, n_joints=1, joint_names=["lever_joint"]), robot)
        assert [(f["effect"], f["joint"]) for f in res.findings_] == [("coulomb_friction", "lever_joint")]
        assert res.findings_[0]["params"]["tau_c"] == pytest.approx(tau_c, rel=0.02)
