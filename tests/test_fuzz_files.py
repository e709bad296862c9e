"""Fuzzing the readers of the files mmgp writes for itself and of settings files (issue 13):
compensator files (JSON and NPZ), saved models (model.json + model.npz) and YAML settings.

Each starts from a valid file and corrupts it at every level its format has (bytes, JSON values,
NPZ arrays, YAML lines). The invariant: a clean error (one line, naming the file) or a correct
result (a compensator whose storage is >= 0 and whose torque is its gradient, a model whose
predictions are finite, settings the estimator accepts), never a traceback, never a changed input.
Size: ``MMGP_FUZZ_SCALE`` multiplies the examples (see tests/fuzz_strategies.py).
"""
from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import event, given
from hypothesis import strategies as st

from fuzz_strategies import assert_clean, digest, fuzz_settings, mutated_bytes, mutated_json, mutated_lines
from mmgp import MultimodalGP
from mmgp.compensator import Compensator, load_compensator
from mmgp.config import load_settings
from mmgp.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "mmgp/resources/replica/replica_log.parquet"


def _compensators() -> dict[str, Compensator]:
    rng = np.random.default_rng(0)
    z1 = np.linspace(-1, 1, 12)[:, None]
    one = Compensator("erf-1dof", z1, rng.normal(size=(12, 1)), [0.4], 2.0, joint_names=["j"])
    z2 = rng.uniform(-1, 1, size=(10, 2))
    two = Compensator("curl-free-rbf", z2, rng.normal(size=(10, 2)), [0.5, 0.7], 1.5)
    return {"erf-1dof": one, "curl-free-rbf": two}


COMPENSATORS = _compensators()


def check_loaded(comp: Compensator) -> None:
    """A compensator that loads is one the checks accept: storage >= 0 on and around its support,
    torque = finite-difference gradient of the storage."""
    q = np.concatenate([comp.support, comp.support + 0.1])
    S = comp.storage(q)
    assert np.all(np.isfinite(S)) and np.all(S >= -1e-9 * max(1.0, comp.storage_offset))
    h = 1e-5
    for i in range(comp.n_joints):
        e = np.zeros(comp.n_joints)
        e[i] = h
        fd = (comp.storage(q + e) - comp.storage(q - e)) / (2 * h)
        scale = max(1.0, float(np.max(np.abs(comp.torque(q)))))
        np.testing.assert_allclose(fd, comp.torque(q)[:, i], atol=1e-4 * scale)


def clean_compensator(path: Path) -> None:
    """``load_compensator``: an InputError naming the file (also for a file it cannot read or whose
    storage offset disagrees with its weights), or a compensator passing :func:`check_loaded`."""
    comp = assert_clean(load_compensator, path)
    if comp is not None:
        check_loaded(comp)


@fuzz_settings(120)
@given(kind=st.sampled_from(list(COMPENSATORS)), data=st.data())
def test_compensator_json_value_corruptions(tmp_path_factory, kind, data):
    path = tmp_path_factory.mktemp("c") / "comp.json"
    d = data.draw(mutated_json(COMPENSATORS[kind].to_dict()))
    path.write_text(json.dumps(d))
    clean_compensator(path)


@fuzz_settings(80)
@given(kind=st.sampled_from(list(COMPENSATORS)), suffix=st.sampled_from([".json", ".npz"]), data=st.data())
def test_compensator_byte_corruptions(tmp_path_factory, kind, suffix, data):
    folder = tmp_path_factory.mktemp("c")
    valid = COMPENSATORS[kind].save(folder / f"valid{suffix}")
    path = folder / f"comp{suffix}"
    path.write_bytes(data.draw(mutated_bytes(valid.read_bytes())))
    clean_compensator(path)


def nasty_arrays() -> st.SearchStrategy[np.ndarray]:
    """Arrays of any dtype NumPy stores without pickling, any small shape, odd values."""
    floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
    shapes = st.lists(st.integers(0, 4), max_size=3).map(tuple)
    return st.one_of(
        shapes.flatmap(lambda s: st.lists(floats, min_size=int(np.prod(s)), max_size=int(np.prod(s)))
                       .map(lambda v, s=s: np.array(v, dtype=np.float64).reshape(s))),
        st.sampled_from([np.array([1, 2], dtype=np.int8), np.array([True]), np.array([1 + 2j]),
                         np.array(["a", "b"]), np.array(3.0), np.zeros((0, 2)), np.array([1e308, -1e308])]))


def _npz_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@st.composite
def mutated_arrays(draw, arrays: dict) -> dict:
    """``arrays`` with one array replaced by a nasty one, removed, or one added."""
    arrays = dict(arrays)
    key = draw(st.sampled_from(sorted(arrays)))
    how = draw(st.sampled_from(["replace", "replace", "drop", "add"]))
    if how == "replace":
        arrays[key] = draw(nasty_arrays())
    elif how == "drop":
        del arrays[key]
    else:
        arrays[draw(st.text(min_size=1, max_size=6).filter(str.isidentifier))] = draw(nasty_arrays())
    return arrays


@fuzz_settings(80)
@given(kind=st.sampled_from(list(COMPENSATORS)), data=st.data())
def test_compensator_npz_array_corruptions(tmp_path_factory, kind, data):
    folder = tmp_path_factory.mktemp("c")
    valid = COMPENSATORS[kind].save(folder / "valid.npz")
    with np.load(valid) as z:
        arrays = {k: z[k] for k in z.files}
    path = folder / "comp.npz"
    path.write_bytes(_npz_bytes(data.draw(mutated_arrays(arrays))))
    clean_compensator(path)


# ---------------------------------------------------------------------------------------------
# Saved models
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def saved_model(tmp_path_factory):
    """A model of the replica lever (one GP on every sample: no sweeps, a few seconds)."""
    d = tmp_path_factory.mktemp("model") / "model"
    MultimodalGP(disturbance=False, max_support=100, final_support=100, fit_iter=10).fit(LOG).save(d)
    return d


def clean_model(folder: Path) -> None:
    """``MultimodalGP.load``: one InputError naming the folder or one of its files, or a model
    whose predictions are finite; neither file changed."""
    files = [folder / "model.json", folder / "model.npz"]
    before = [digest(p) if p.exists() else None for p in files]
    try:
        model = MultimodalGP.load(folder)
    except InputError as err:
        assert "\n" not in str(err) and err.file in {str(folder), *map(str, files)}, str(err)
        event("InputError: " + err.message[:30])
    else:
        n = len(model.joint_names_)
        q = np.full((3, n), 0.5)
        mean, std = model.predict(q, np.zeros_like(q), np.zeros_like(q))
        assert np.all(np.isfinite(mean)) and np.all(std > 0)
        event("loaded")
    assert [digest(p) if p.exists() else None for p in files] == before, "the reader changed its input"


def _model_copy(saved_model: Path, tmp_path_factory) -> Path:
    return Path(shutil.copytree(saved_model, tmp_path_factory.mktemp("m") / "model"))


@fuzz_settings(100)
@given(data=st.data())
def test_model_json_value_corruptions(saved_model, tmp_path_factory, data):
    folder = _model_copy(saved_model, tmp_path_factory)
    meta = json.loads((folder / "model.json").read_text())
    (folder / "model.json").write_text(json.dumps(data.draw(mutated_json(meta))))
    clean_model(folder)


@fuzz_settings(60)
@given(which=st.sampled_from(["model.json", "model.npz"]), data=st.data())
def test_model_byte_corruptions(saved_model, tmp_path_factory, which, data):
    folder = _model_copy(saved_model, tmp_path_factory)
    path = folder / which
    path.write_bytes(data.draw(mutated_bytes(path.read_bytes())))
    clean_model(folder)


@fuzz_settings(60)
@given(data=st.data())
def test_model_npz_array_corruptions(saved_model, tmp_path_factory, data):
    folder = _model_copy(saved_model, tmp_path_factory)
    with np.load(folder / "model.npz") as z:
        arrays = {k: z[k] for k in z.files}
    (folder / "model.npz").write_bytes(_npz_bytes(data.draw(mutated_arrays(arrays))))
    clean_model(folder)


# ---------------------------------------------------------------------------------------------
# Settings files
# ---------------------------------------------------------------------------------------------

DEFAULT_YAML = (ROOT / "configs/default.yaml").read_text()


def clean_settings(path: Path) -> None:
    """load_settings: an InputError on one line naming the file (unknown names, invalid YAML, a
    bad value), or settings the estimator accepts."""
    def reader(p):
        settings = load_settings(p, "train", MultimodalGP)
        MultimodalGP(**settings)._validate()
        return settings

    assert_clean(reader, path)


@fuzz_settings(120)
@given(data=st.data())
def test_settings_yaml_line_corruptions(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("s") / "settings.yaml"
    path.write_text(data.draw(mutated_lines(DEFAULT_YAML, sep=":")))
    clean_settings(path)


@fuzz_settings(120)
@given(data=st.data())
def test_settings_value_corruptions(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("s") / "settings.yaml"
    sections = {"train": yaml.safe_load(DEFAULT_YAML)["train"]}
    mutated = data.draw(mutated_json(sections))
    path.write_text(yaml.safe_dump(mutated) if data.draw(st.booleans()) else json.dumps(mutated))
    clean_settings(path)


@fuzz_settings(40)
@given(data=st.data())
def test_settings_byte_corruptions(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("s") / "settings.yaml"
    path.write_bytes(data.draw(mutated_bytes(DEFAULT_YAML.encode())))
    clean_settings(path)
