"""Selection on synthetic residuals, and end-to-end diagnosis of short MuJoCo recordings."""
import json

import numpy as np
import pytest

from mmgp import concealed as C
from mmgp import effects as fx
from mmgp.diagnose import FoldGrams, ForwardCVSelector, diagnose
from mmgp.signals import time_block_folds


def _synthetic_ctx(T=3000, n=3, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 30, T)
    q = np.stack([np.sin(0.3 * t * (j + 1) + j) for j in range(n)], 1)
    dq = np.gradient(q, t, axis=0)
    ddq = np.gradient(dq, t, axis=0)
    tau_rbd = 5 * np.cos(q)
    ctx = fx.Context(q, dq, ddq, tau_rbd, np.zeros((T, n, n)), np.zeros((T, n, 10 * n)), np.full(n, 0.02),
                     [f"j{j}" for j in range(n)], [f"l{j}" for j in range(n)])
    return ctx, rng


def _select(ctx, r):
    lib = fx.effect_library(ctx, effects=[e for e in fx.JOINT_EFFECTS if e != "encoder_offset"])
    keys, A = fx.build_atoms(lib, ctx)
    grams = FoldGrams(A, r, np.ones(ctx.T, bool), time_block_folds(ctx.T, 8))
    return ForwardCVSelector().fit(lib, keys, grams, np.ones(ctx.n)).selected_


def test_selection_recovers_planted_effect():
    ctx, rng = _synthetic_ctx()
    r = 0.1 * rng.standard_normal((ctx.T, ctx.n))
    r[:, 1] += 0.3 * np.tanh(ctx.dq[:, 1] / 0.02)  # Coulomb at 3x the noise level on joint 1
    assert [(e.name, e.index) for e in _select(ctx, r)] == [("coulomb_friction", 1)]


def test_selection_rejects_pure_noise():
    for seed in range(3):
        ctx, rng = _synthetic_ctx(seed=seed)
        r = 0.1 * rng.standard_normal((ctx.T, ctx.n))
        assert _select(ctx, r) == []


@pytest.fixture(scope="module")
def cases():
    out = {}
    for name in ("panda_coulomb_j4", "panda_control", "actuator_load_friction", "panda_payload"):
        spec = dict(next(s for s in C.STANDARD_CASES if s["name"] == name), n_samples=2000)
        rec, truth = C.make_case(spec, seed=2)
        out[name] = (spec, rec, truth)
    return out


def _run(case, **cfg):
    spec, rec, truth = case
    return diagnose(C.recording_to_log(rec), C.nominal_robot(spec), config={"gp": False, "plots": False, **cfg}), truth


def _effects(res):
    return [f for f in res.findings if f["effect"] not in ("external_disturbance", "mode_switch")]


def test_finds_concealed_coulomb(cases):
    res, truth = _run(cases["panda_coulomb_j4"])
    f = _effects(res)
    assert [(x["effect"], x["joint"]) for x in f] == [("coulomb_friction", "panda_joint4")]
    assert f[0]["params"]["tau_c"] == pytest.approx(1.5, rel=0.1)
    assert res.fit["with_physics"]["nmse"]["panda_joint4"] < 0.5 * res.fit["nominal"]["nmse"]["panda_joint4"]


def test_finds_load_dependent_friction_on_actuator(cases):
    res, truth = _run(cases["actuator_load_friction"])
    # known weakness (see the report): on this short 1-DOF log extra effects may be kept too
    f = [x for x in _effects(res) if x["effect"] == "load_dependent_friction"]
    assert len(f) == 1
    assert f[0]["params"]["tau_c"] == pytest.approx(0.3, rel=0.25)
    assert f[0]["params"]["beta"] == pytest.approx(0.2, rel=0.25)


def test_finds_payload_mass(cases):
    res, truth = _run(cases["panda_payload"])
    pl = [f for f in res.findings if f["effect"] == "payload"]
    assert len(pl) == 1 and pl[0]["link"] == "panda_link7"
    assert pl[0]["params"]["mass"] == pytest.approx(1.2, rel=0.1)
    assert pl[0]["params"]["com"][2] == pytest.approx(0.15, abs=0.03)


def test_control_case_has_no_finding(cases, tmp_path):
    res, truth = _run(cases["panda_control"])
    assert res.findings == []
    res.write(tmp_path)
    doc = json.loads((tmp_path / "findings.json").read_text())
    assert doc["findings"] == [] and set(doc["fit"]) >= {"nominal", "with_physics"}
    assert "Nothing is missing" in (tmp_path / "report.md").read_text()
