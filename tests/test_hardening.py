"""Issue 13, the cases left open: each bad input reproduced through the command line, answered by
one line naming the file and exit status 2 (1 for a failed check), no traceback, inputs untouched,
no failing output left behind."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mmgp import MultimodalGP
from mmgp.cli import app
from mmgp.compensator import load_compensator
from mmgp.data.folds import windows_for_duration
from mmgp.data.logs import write_log
from mmgp.errors import InputError
from mmgp.physics.robot import RobotModel
from test_outputs import unprivileged  # run as a user that permissions apply to

ROOT = Path(__file__).resolve().parents[1]
REPLICA = ROOT / "mmgp/resources/replica"
LOG = REPLICA / "replica_log.parquet"
LABELS = REPLICA / "replica_labels.parquet"
URDF = REPLICA / "replica_lever.urdf"
runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def one_error_line(res, code: int = 2, names=None) -> str:
    """The result failed with ``code`` and one line on stderr (naming ``names`` when given)."""
    assert res.exit_code == code, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    if names is not None:
        assert str(names) in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A model of the replica lever (one GP, no sweeps: seconds) and its exported compensator."""
    d = tmp_path_factory.mktemp("base")
    MultimodalGP(disturbance=False).fit(LOG).save(d / "model")
    res = run("export", d / "model", "--out", d / "comp.json")
    assert res.exit_code == 0, res.output
    return d


def damaged_copy(src: Path, dst: Path, fix) -> Path:
    shutil.copytree(src, dst)
    fix(dst)
    return dst


# ---------------------------------------------------------------------------------------------
# Saved models
# ---------------------------------------------------------------------------------------------

MODEL_DAMAGES = {
    "truncated npz": (lambda d: (d / "model.npz").write_bytes((d / "model.npz").read_bytes()[:300]), "model.npz"),
    "invalid json": (lambda d: (d / "model.json").write_text('{"format": "mmgp-model", '), "model.json"),
    "missing npz": (lambda d: (d / "model.npz").unlink(), "model.npz missing"),
    "json list": (lambda d: (d / "model.json").write_text("[1, 2]"), "model.json"),
    "version null": (lambda d: _edit_json(d / "model.json", version=None), "version null"),
    "joint names not a list": (lambda d: _edit_json(d / "model.json", joint_names="q"), "joint_names"),
    "unknown setting": (lambda d: _edit_json(d / "model.json", settings={"colour": 1}), "settings"),
    "bad setting value": (lambda d: _edit_json(d / "model.json", settings={"max_sweeps": "many"}), "max_sweeps"),
    "setting beyond int64": (lambda d: _edit_json(d / "model.json", settings={"push_s": -2 ** 63 - 1}), "push_s"),
    "array missing": (lambda d: _edit_npz(d / "model.npz", drop="Y_0"), "Y_0"),
    "array of another shape": (lambda d: _edit_npz(d / "model.npz", X_0=np.zeros((3, 2))), "X_0"),
    "array not finite": (lambda d: _edit_npz(d / "model.npz", noise_var_0=np.array([np.nan])), "noise_var_0"),
    "weights digest not a list": (lambda d: _edit_json(d / "model.json", gp_weights_sha256="ab"), "gp_weights_sha256"),
    "sign fade not a boolean": (lambda d: _edit_json(d / "model.json", sign_fades="false"), "sign_fades"),
    "weights of another shape": (lambda d: _edit_npz(d / "model.npz", weights_0=np.zeros((1, 3))), "weights_0"),
}


def _edit_json(path: Path, **changes):
    meta = json.loads(path.read_text())
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(meta.get(key), dict):
            meta[key].update(value)
        else:
            meta[key] = value
    path.write_text(json.dumps(meta))


def _edit_npz(path: Path, drop: str | None = None, **arrays):
    with np.load(path) as z:
        content = {k: z[k] for k in z.files if k != drop}
    content.update(arrays)
    with open(path, "wb") as fh:
        np.savez(fh, **content)


@pytest.mark.parametrize("damage", list(MODEL_DAMAGES))
def test_damaged_saved_model_is_one_error_line(base, tmp_path, damage):
    fix, expected = MODEL_DAMAGES[damage]
    model = damaged_copy(base / "model", tmp_path / "model", fix)
    res = run("predict", model, LOG, "--out", tmp_path / "p.parquet")
    line = one_error_line(res, names=model)
    assert expected in line
    assert not (tmp_path / "p.parquet").exists()
    with pytest.raises(InputError):
        MultimodalGP.load(model)


def test_undamaged_saved_model_still_loads(base):
    model = MultimodalGP.load(base / "model")
    q = np.linspace(0.2, 1.0, 5)[:, None]
    mean = model.predict(q, np.zeros_like(q), np.zeros_like(q), return_std=False)
    assert mean.shape == (5, 1) and np.all(np.isfinite(mean))


# ---------------------------------------------------------------------------------------------
# Compensator files: check-passivity and load_compensator validate the same things
# ---------------------------------------------------------------------------------------------

def _without(key):
    return lambda d: {k: v for k, v in d.items() if k != key}


COMP_DAMAGES = {
    "version null": (lambda d: {**d, "version": None}, "version None"),
    "version as text": (lambda d: {**d, "version": "1"}, "version '1'"),
    "no kind": (_without("kind"), "'kind'"),
    "no storage_offset": (_without("storage_offset"), "'storage_offset'"),
    "a JSON list": (lambda d: [d], "found a list"),
    "bounds of 1e308": (lambda d: {**d, "workspace_bounds": [[-1e308], [1e308]]}, "workspace_bounds"),
    "negative lengthscale": (lambda d: {**d, "lengthscales": [-1.0]}, "lengthscales"),
    "support as text": (lambda d: {**d, "support": "abc"}, "support"),
    "storage sampled below its bound": (lambda d: {**d, "storage_sampled_min": -5.0}, "below its lower bound"),
    "another stated lower bound": (lambda d: {**d, "storage_lower_bound": 5.0}, "storage_lower_bound"),
}


@pytest.mark.parametrize("damage", list(COMP_DAMAGES))
def test_damaged_compensator_file_is_refused_by_check_and_loader(base, tmp_path, damage):
    mod, expected = COMP_DAMAGES[damage]
    path = tmp_path / "comp.json"
    path.write_text(json.dumps(mod(json.loads((base / "comp.json").read_text()))))
    before = path.read_bytes()
    line = one_error_line(run("check-passivity", path), names=path)
    assert expected in line
    with pytest.raises(InputError) as info:
        load_compensator(path)
    assert info.value.file == str(path)
    assert path.read_bytes() == before


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_truncated_compensator_file(base, tmp_path, suffix):
    full = tmp_path / f"full{suffix}"
    assert run("export", base / "model", "--out", full).exit_code == 0
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(full.read_bytes()[: len(full.read_bytes()) // 2])
    one_error_line(run("check-passivity", cut), names=cut)
    with pytest.raises(InputError, match="not a readable mmgp-compensator file") as info:
        load_compensator(cut)
    assert info.value.file == str(cut)


def _not_a_compensator(base, path: Path) -> None:
    if path.suffix == ".npz":
        shutil.copy(base / "model" / "model.npz", path)  # an NPZ archive, but a saved model's
    else:
        path.write_text("t,q_0,tau_0\n0,1,2\n")


@pytest.mark.parametrize("suffix", [".json", ".npz", ".yaml"])
def test_file_that_is_not_a_compensator_at_all(base, tmp_path, suffix):
    path = tmp_path / f"other{suffix}"
    _not_a_compensator(base, path)
    before = path.read_bytes()
    with pytest.raises(InputError) as info:
        load_compensator(path)
    assert info.value.file == str(path) and "mmgp-compensator" in info.value.message
    assert isinstance(info.value, ValueError)  # callers catching ValueError still catch it
    one_error_line(run("check-passivity", path), names=path)
    assert path.read_bytes() == before


def test_compensator_with_another_storage_offset(base, tmp_path):
    d = json.loads((base / "comp.json").read_text())
    true_offset = d["storage_offset"]
    d["storage_offset"] = true_offset + 1.0
    path = tmp_path / "offset.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError) as info:
        load_compensator(path)
    assert info.value.file == str(path)
    assert "'storage_offset'" in info.value.message and repr(true_offset) in info.value.message
    line = one_error_line(run("check-passivity", path), names=path)
    assert "storage_offset" in line


def test_compensator_that_cannot_be_rebuilt_is_an_input_error(base, tmp_path):
    d = json.loads((base / "comp.json").read_text())
    d["kernel"] = {"smoothness": "three"}
    path = tmp_path / "kernel.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError, match="cannot rebuild the compensator") as info:
        load_compensator(path)
    assert info.value.file == str(path)


def _damage_npy_header(src: Path, dst: Path) -> Path:
    """``src`` (an NPZ) with the first array's .npy header made unbalanced: NumPy's header parser
    (Python's tokenizer) raised TokenError, which no reader caught (found by the random fuzz)."""
    import zipfile

    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for i, info in enumerate(zin.infolist()):
            data = zin.read(info)
            zout.writestr(info, data.replace(b"{'descr'", b"(('descr'", 1) if i == 0 else data)
    return dst


def test_npy_header_the_tokenizer_fails_on(base, tmp_path):
    export = tmp_path / "full.npz"
    assert run("export", base / "model", "--out", export).exit_code == 0
    comp = _damage_npy_header(export, tmp_path / "comp.npz")
    with pytest.raises(InputError, match="not a readable mmgp-compensator file") as info:
        load_compensator(comp)
    assert info.value.file == str(comp)
    model = damaged_copy(base / "model", tmp_path / "model", lambda d: (d / "model.npz").unlink())
    _damage_npy_header(base / "model" / "model.npz", model / "model.npz")
    with pytest.raises(InputError, match="model.npz is damaged") as info:
        MultimodalGP.load(model)
    assert info.value.file == str(model / "model.npz")


def test_valid_compensator_passes_check(base):
    res = run("check-passivity", base / "comp.json", "--configs", "20", "--loops", "5")
    assert res.exit_code == 0, res.output
    assert "passed: True" in res.stdout


# ---------------------------------------------------------------------------------------------
# export: a joint that never moves; a field that fails its check is never written
# ---------------------------------------------------------------------------------------------

def test_export_of_a_joint_that_never_moves(tmp_path):
    rng = np.random.default_rng(0)
    t = np.arange(200) * 0.05
    log = write_log(tmp_path / "still.parquet", t, np.full((200, 1), 0.5), 2.0 + 0.01 * rng.normal(size=(200, 1)))
    MultimodalGP(disturbance=False).fit(log).save(tmp_path / "model")
    out = tmp_path / "comp.json"
    line = one_error_line(run("export", tmp_path / "model", "--out", out), names=tmp_path / "model")
    assert "never move" in line
    assert not out.exists()


def test_export_never_leaves_a_failing_file(base, tmp_path, monkeypatch):
    import mmgp.compensator as comp_pkg

    real = comp_pkg.check_passivity

    def failing(comp, **kw):
        return {**real(comp, n_configs=5, n_loops=2), "passed": False, "loop_pass": False}

    monkeypatch.setattr(comp_pkg, "check_passivity", failing)
    out = tmp_path / "comp.json"
    res = run("export", base / "model", "--out", out, "--c", tmp_path / "comp")
    line = one_error_line(res, code=1, names=base / "model")
    assert "fails the passivity check" in line and "nothing written" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# Logs against the robot, the clock, windows
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def one_dof_panda(tmp_path_factory):
    d = tmp_path_factory.mktemp("panda1")
    lg = pd.read_parquet(LOG)
    plain = write_log(d / "plain.parquet", lg["t"], lg[["q_0"]], lg[["tau_0"]])
    meta = write_log(d / "meta.parquet", lg["t"], lg[["q_0"]], lg[["tau_0"]], robot="panda")
    return plain, meta


@pytest.mark.parametrize("command", ["train", "diagnose"])
def test_one_dof_log_on_a_seven_joint_robot_is_refused(one_dof_panda, tmp_path, command):
    plain, meta = one_dof_panda
    for args in ([plain, "--robot", "panda"], [meta]):
        res = run(command, *args, "--out", tmp_path / "out", "--quiet", "--force")
        line = one_error_line(res, names=args[0])
        assert "panda_joint2" in line and "1 joint" in line
        assert not (tmp_path / "out").exists()


def test_gripper_fingers_are_the_only_joints_a_log_may_leave_out():
    assert len(RobotModel.from_name("panda", n_joints=7).joint_names) == 7  # fingers locked
    for n in (1, 6):
        with pytest.raises(InputError, match="panda_joint7"):
            RobotModel.from_name("panda", n_joints=n)
    # naming the joints still selects any subset deliberately
    assert RobotModel.from_name("panda", ["panda_joint1"]).joint_names == ["panda_joint1"]


def test_clock_jump_of_epoch_seconds(tmp_path, base):
    lg = pd.read_parquet(LOG)
    t = lg["t"].to_numpy().copy()
    t[200:] += 1.7e9
    log = write_log(tmp_path / "jump.parquet", t, lg[["q_0"]], lg[["tau_0"]])
    for args in (["train", log, "--out", tmp_path / "o1", "--quiet"],
                 ["predict", base / "model", log, "--out", tmp_path / "p.parquet"],
                 ["diagnose", log, "--urdf", URDF, "--out", tmp_path / "o2", "--quiet"]):
        line = one_error_line(run(*args), names=log)
        assert "row 200" in line and "jumps by 1.7e+09 s" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["jump.parquet"]


def test_duplicate_csv_header_column(tmp_path):
    lg = pd.read_parquet(LOG)
    text = "t,q_0,tau_0,q_0\n" + "".join(f"{a},{b},{c},{b + 1}\n" for a, b, c in lg[["t", "q_0", "tau_0"]].to_numpy())
    path = tmp_path / "dup.csv"
    path.write_text(text)
    line = one_error_line(run("train", path, "--out", tmp_path / "out", "--quiet"), names=path)
    assert "appears twice" in line and "'q_0'" in line


def test_malformed_urdf_and_invalid_yaml_are_one_line(tmp_path):
    urdf = tmp_path / "bad.urdf"
    urdf.write_text('<?xml version="1.0"?>\n<robot name="x">\n<link name="a">\n<joint name="j" type="revolute">\n')
    yml = tmp_path / "bad.yaml"
    yml.write_text("train:\n  n_modes: [2\n  seed: 1\n")
    # The C++ parser writes to file descriptor 2 itself, which only a separate process shows.
    proc = subprocess.run([sys.executable, "-m", "mmgp.cli", "train", str(LOG), "--urdf", str(urdf), "--out",
                           str(tmp_path / "o"), "--quiet"], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(urdf) in lines[0] and "Line number=4" in lines[0], proc.stderr
    line = one_error_line(run("train", LOG, "--config", yml, "--out", tmp_path / "o", "--quiet"), names=yml)
    assert "not valid YAML" in line


BAD_SETTING_VALUES = {
    "negative count": ("train", "train:\n  max_sweeps: -3\n", "max_sweeps"),
    "text for a number": ("train", "train:\n  push_s: soon\n", "push_s"),
    "unknown choice": ("diagnose", "diagnose:\n  separate: sideways\n", "separate"),
    "export count of zero": ("export", "export:\n  max_support: 0\n", "max_support"),
    "export count as text": ("export", "export:\n  max_support: many\n", "max_support"),
    "export negative seed": ("export", "export:\n  seed: -1\n", "seed"),
    "integer beyond int64": ("train", "train:\n  stay_prob: -9223372036854775809\n", "stay_prob"),
}


@pytest.mark.parametrize("case", list(BAD_SETTING_VALUES))
def test_bad_setting_value_names_the_settings_file(base, tmp_path, case):
    command, text, key = BAD_SETTING_VALUES[case]
    yml = tmp_path / "settings.yaml"
    yml.write_text(text)
    first = {"train": [LOG], "diagnose": [LOG, "--urdf", URDF], "export": [base / "model"]}[command]
    out = tmp_path / ("comp.json" if command == "export" else "out")
    res = run(command, *first, "--config", yml, "--out", out, *(["--quiet"] if command != "export" else []))
    line = one_error_line(res, names=yml)
    assert f"setting '{key}'" in line
    assert not out.exists() and yml.read_text() == text


def test_bad_flag_value_is_not_blamed_on_the_settings_file(tmp_path):
    from mmgp.config import load_settings

    yml = tmp_path / "settings.yaml"
    yml.write_text("train:\n  max_sweeps: -3\n  seed: 2\n")
    # the flag replaces the file's bad value: accepted
    assert load_settings(yml, "train", MultimodalGP, max_sweeps=4) == {"max_sweeps": 4, "seed": 2}
    yml.write_text("train:\n  seed: 2\n")
    with pytest.raises(InputError, match="setting 'max_sweeps'") as info:
        load_settings(yml, "train", MultimodalGP, max_sweeps=0)
    assert info.value.file is None


ROBOT_DAMAGES = {
    "unknown robot": ({"robot": "no_such_robot", "urdf": None, "joint_names": ["j0"]}, "no_such_robot"),
    "missing URDF": ({"robot": None, "urdf": "/nonexistent/arm.urdf", "joint_names": ["j0"]}, "arm.urdf"),
    "robot not a name": ({"robot": 7, "urdf": None}, "'robot'"),
}


@pytest.mark.parametrize("damage", list(ROBOT_DAMAGES))
def test_saved_model_naming_a_robot_that_cannot_be_loaded(base, tmp_path, damage):
    spec, expected = ROBOT_DAMAGES[damage]
    model = damaged_copy(base / "model", tmp_path / "model", lambda d: _edit_json(d / "model.json", robot=spec))
    meta_path = model / "model.json"
    before = meta_path.read_bytes()
    with pytest.raises(InputError) as info:
        MultimodalGP.load(model)
    assert info.value.file == str(meta_path) and expected in info.value.message
    res = run("predict", model, LOG, "--out", tmp_path / "p.parquet")
    assert expected in one_error_line(res, names=meta_path)
    assert meta_path.read_bytes() == before and not (tmp_path / "p.parquet").exists()


@pytest.mark.parametrize("device", ["mps", "meta"])
def test_device_torch_knows_but_the_gps_do_not_run_on(tmp_path, device):
    res = run("compare", LOG, "--urdf", URDF, "--out", tmp_path / "out", "--quiet", "--device", device)
    assert f"device '{device}' is not supported" in one_error_line(res)
    assert not (tmp_path / "out").exists()


def test_compare_with_too_few_training_samples_is_a_usage_error(tmp_path):
    res = run("compare", LOG, "--urdf", URDF, "--out", tmp_path / "out", "--quiet", "--max-train", "0")
    assert res.exit_code == 2 and isinstance(res.exception, SystemExit) and "--max-train" in res.stderr
    assert not (tmp_path / "out").exists()


def test_compare_on_a_log_too_short_for_its_folds(tmp_path):
    short = tmp_path / "short.csv"
    pd.read_parquet(LOG).iloc[:10].to_csv(short, index=False)
    res = run("compare", short, "--urdf", URDF, "--out", tmp_path / "out", "--quiet")
    assert "too short to compare" in one_error_line(res, names=short)
    assert not (tmp_path / "out").exists()


def test_quiet_train_prints_nothing_before_its_error(tmp_path):
    path = tmp_path / "dup.csv"
    path.write_text("t,q_0,tau_0,q_0\n0,0,0,0\n")
    res = run("train", path, "--out", tmp_path / "out", "--quiet")
    one_error_line(res)
    assert res.stdout == ""


def test_windows_capped_at_their_fraction_of_the_log():
    assert windows_for_duration(0.5, exclusion_s=1.0, block_s=2.0, mode_smoothing_s=4.0) == \
        pytest.approx({"exclusion_s": 0.1, "block_s": 0.2, "mode_smoothing_s": 0.4})
    assert windows_for_duration(5.0, exclusion_s=1.0, block_s=2.0, mode_smoothing_s=4.0) == {}
    assert windows_for_duration(2.0, exclusion_s=0.0, block_s=2.0) == {"block_s": pytest.approx(0.8)}


def test_log_shorter_than_the_exclusion_window_flags_the_push_only():
    # 0.04 s at 10 kHz, a lever swinging through a sine torque, pushed on rows 160..183: the 1 s
    # exclusion window covered the whole log, every prediction was the GP's prior and the whole
    # push went unflagged (0 of 24). The same samples over 4 s at 100 Hz flag exactly the push.
    rng = np.random.default_rng(0)
    i = np.arange(400)
    q = 1.2 * np.sin(2 * np.pi * i / 200.0)
    tau = 5.0 * np.sin(q) + 0.02 * rng.normal(size=400)
    tau[160:184] += 1.5
    model = MultimodalGP(max_sweeps=8, fit_points=150, fit_iter=20).fit(t=i / 1e4, q=q[:, None], tau=tau[:, None])
    np.testing.assert_array_equal(np.flatnonzero(model.disturbed_), np.arange(160, 184))
    assert model.report_["windows_shortened_s"] == pytest.approx(
        {"exclusion_s": 0.2 * 0.0399, "block_s": 0.4 * 0.0399, "mode_smoothing_s": 0.8 * 0.0399,
         "min_push_s": 0.03 * 0.0399, "min_mode_s": 0.8 * 0.0399, "push_scan_s": 0.04 * 0.0399})


# ---------------------------------------------------------------------------------------------
# Read-only --out of every writing command
# ---------------------------------------------------------------------------------------------

def test_read_only_out_of_train_predict_export_evaluate(base):
    shared = Path(tempfile.mkdtemp(prefix="mmgp-ro-test-"))
    try:
        os.chmod(shared, 0o755)
        log = Path(shutil.copy(LOG, shared / "log.parquet"))
        truth = Path(shutil.copy(LABELS, shared / "truth.parquet"))
        model = shutil.copytree(base / "model", shared / "model")
        pd.DataFrame({"t": pd.read_parquet(LOG)["t"], "mode": 0, "disturbed": 0,
                      "p_disturbed": 0.0}).to_parquet(model / "labels.parquet")
        ro = shared / "ro"
        ro.mkdir()
        for p in (ro, model):
            os.chmod(p, 0o555)
        cases = [(["train", log, "--out", ro / "run", "--quiet"], ro / "run"),
                 (["predict", model, log, "--out", ro / "p.parquet"], ro / "p.parquet"),
                 (["export", model, "--out", ro / "c.json"], ro / "c.json"),
                 (["evaluate", model, "--truth", truth], model / "evaluation.json")]
        for args, out in cases:
            with unprivileged():
                res = run(*args)
            assert "not writable" in one_error_line(res, names=out)
        assert list(ro.iterdir()) == [] and not (model / "evaluation.json").exists()
    finally:
        for p in [shared, *shared.rglob("*")]:
            if p.is_dir():
                os.chmod(p, 0o755)
        shutil.rmtree(shared)


def test_duplicate_parquet_column_named_by_diagnose_too(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    lg = pd.read_parquet(LOG)
    path = tmp_path / "dup.parquet"
    arrays = [pa.array(lg[c]) for c in ("t", "q_0", "tau_0")] + [pa.array(lg["q_0"] + 1)]
    pq.write_table(pa.Table.from_arrays(arrays, names=["t", "q_0", "tau_0", "q_0"]), path)
    for args in (["train", path], ["diagnose", path, "--urdf", URDF]):
        line = one_error_line(run(*args, "--out", tmp_path / "out", "--quiet"), names=path)
        assert "column 'q_0'" in line and "appears twice" in line and "q_1" not in line
