"""Stored GP weights: a large exact GP's solved weights K^-1 y travel with the saved model, so
``mmgp export`` predicts the nominal torque without refactorising (benchmarks/bench_export_time.py).

References: the GP posterior mean in closed form with numpy (``np.linalg.solve`` on the kernel in
data units, no torch, no Cholesky of the package), and the export of the same saved model with
its weights removed, which solves them afresh (the path of models saved before weights were
stored). Every exact GP is made "large" (``per_output_``) by lowering ``BATCHED_BYTES``, so the
stored path runs on a model small enough to train in seconds.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import mmgp.gp.exact as exact
from mmgp import MultimodalGP
from mmgp.gp.exact import ExactGP

REPLICA_LOG = Path(__file__).resolve().parents[1] / "mmgp" / "resources" / "replica" / "replica_log.parquet"


def _numpy_posterior_mean(gp: ExactGP, X, Y, Xq) -> np.ndarray:
    """Posterior mean (M, m) of independent RBF GPs in data units, from the fit's hyperparameters."""
    ym, ys = Y.mean(0), Y.std(0)
    out = np.empty((len(Xq), Y.shape[1]))
    for j in range(Y.shape[1]):
        l = gp.lengthscale_[j]
        s2 = gp.hyper_.signal_var[j] * ys[j] ** 2
        k = lambda A, B: s2 * np.exp(-0.5 * np.sum(((A[:, None] - B[None]) / l) ** 2, axis=2))  # noqa: E731
        K = k(X, X) + gp.noise_std_[j] ** 2 * np.eye(len(X))
        out[:, j] = ym[j] + k(Xq, X) @ np.linalg.solve(K, Y[:, j] - ym[j])
    return out


def _no_factorisation(*a, **k):
    raise AssertionError("the stored weights were not used")


def test_stored_weights_predict_without_factorising(monkeypatch):
    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, size=(300, 3))
    Y = np.stack([np.sin(X[:, 0]) * X[:, 1], np.cos(X[:, 2])], 1) + 0.05 * rng.normal(size=(300, 2))
    Xq = rng.uniform(-2, 2, size=(200, 3))
    monkeypatch.setattr(exact, "BATCHED_BYTES", 0)  # one output at a time, solved when first predicted
    first = ExactGP(max_iter=20, seed=0).fit(X, Y)
    assert first.per_output_ and first.solved_weights() is None
    ref = _numpy_posterior_mean(first, X, Y, Xq)
    np.testing.assert_allclose(first.predict(Xq, return_std=False), ref, rtol=0, atol=1e-8)
    w = first.solved_weights()
    assert w.shape == (2, 300)

    monkeypatch.setattr(exact, "robust_cholesky", _no_factorisation)
    again = ExactGP(hyper=first.hyper_, optimise=False).fit(X, Y, weights=w)
    # closed form vs stored weights: both exact, they differ by rounding (kernel ~1, |y| ~1)
    np.testing.assert_allclose(again.predict(Xq, return_std=False), ref, rtol=0, atol=1e-8)
    with pytest.raises(ValueError, match="weights must be"):
        ExactGP(hyper=first.hyper_, optimise=False).fit(X, Y, weights=w[:, :10])


def test_cross_kernel_is_the_rbf_kernel():
    """The prediction kernel (one augmented product) against the RBF formula, numpy differences."""
    import torch

    from mmgp.gp.kernels import rbf_cross_kernel

    rng = np.random.default_rng(1)
    X1, X2 = rng.normal(size=(50, 6)), rng.normal(size=(40, 6)) * 3
    X2[:5] = X1[:5]  # coincident points: the kernel's peak, where the product form cancels most
    l, s2 = rng.uniform(0.5, 3.0, size=6), 2.7
    ref = s2 * np.exp(-0.5 * np.sum(((X1[:, None] - X2[None]) / l) ** 2, axis=2))
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    got = rbf_cross_kernel(t(X1), t(X2), t(l), t(s2)).numpy()
    # rounding of |A|^2 + |B|^2 - 2 A.B (|A|^2 up to ~50 here) before exp: ~50 * 1e-16 relative
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-300)
    assert np.all(got <= s2)


@pytest.fixture(scope="module")
def saved_models(tmp_path_factory):
    """A replica-lever model saved with its solved weights, and a copy without them."""
    res = MultimodalGP(max_sweeps=8, seed=0).fit(REPLICA_LOG)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(exact, "BATCHED_BYTES", 0)
        res._gps[0] = None  # rebuilt as a large GP (the EM's windowed GPs need small ones)
        q = np.linspace(res.support_q_.min(), res.support_q_.max(), 50)[:, None]
        res.nominal_torque(q)  # solves the nominal GP's weights (training's friction check does too)
        fast = tmp_path_factory.mktemp("fast")
        res.save(fast)
    slow = tmp_path_factory.mktemp("slow")
    with np.load(fast / "model.npz") as z:
        arrays = {k: z[k] for k in z.files if not k.startswith("weights_")}
    np.savez(slow / "model.npz", **arrays)
    meta = json.loads((fast / "model.json").read_text())
    assert meta["gp_weights_sha256"][0] is not None and "weights_0" not in arrays
    meta.pop("gp_weights_sha256")
    (slow / "model.json").write_text(json.dumps(meta))
    return fast, slow


def test_export_with_stored_weights_matches_the_exact_solve(saved_models, monkeypatch):
    fast, slow = saved_models
    monkeypatch.setattr(exact, "BATCHED_BYTES", 0)
    m_fast, m_slow = MultimodalGP.load(fast), MultimodalGP.load(slow)
    assert m_fast.gp_weights_[0] is not None and m_slow.gp_weights_[0] is None
    c_slow = m_slow.to_compensator(max_support=200, seed=0)
    monkeypatch.setattr(exact, "robust_cholesky", _no_factorisation)  # the model GP's, not the export's
    c_fast = m_fast.to_compensator(max_support=200, seed=0)
    q = np.linspace(c_slow.bounds[0, 0] - 0.2, c_slow.bounds[1, 0] + 0.2, 2000)[:, None]
    scale = np.max(np.abs(c_slow.torque(q)))
    # The stored weights are the training's solve of the same system: what differs is rounding,
    # amplified at most by the kernel system's conditioning; 1e-9 of the torque scale is far
    # below the model's own noise (about 1e-2 of it here).
    assert np.max(np.abs(c_fast.torque(q) - c_slow.torque(q))) <= 1e-9 * scale


def _edit_support(src: Path, dst: Path, keep_weights: bool) -> None:
    """Copy a saved model with a smooth function of position added to its GP targets."""
    shutil.copytree(src, dst)
    with np.load(dst / "model.npz") as z:
        arrays = {k: z[k] for k in z.files if keep_weights or not k.startswith("weights_")}
    arrays["Y_0"] = arrays["Y_0"] + 0.5 * np.sin(3.0 * arrays["X_0"][:, :1])
    np.savez(dst / "model.npz", **arrays)


def test_edited_model_does_not_use_stale_weights(saved_models, tmp_path, monkeypatch):
    """Targets edited after saving no longer match the weights' digest: the weights are solved
    again, and the model predicts what a model saved without weights predicts."""
    fast, slow = saved_models
    monkeypatch.setattr(exact, "BATCHED_BYTES", 0)
    _edit_support(fast, tmp_path / "kept", keep_weights=True)
    _edit_support(slow, tmp_path / "none", keep_weights=False)
    kept, none = MultimodalGP.load(tmp_path / "kept"), MultimodalGP.load(tmp_path / "none")
    assert kept.gp_weights_[0] is None
    q = np.linspace(kept.support_q_.min(), kept.support_q_.max(), 100)[:, None]
    ref = none.nominal_torque(q)
    assert np.max(np.abs(kept.nominal_torque(q) - ref)) <= 1e-9 * np.max(np.abs(ref))
    # what the digest prevents: the stale weights would miss the edit by about its size
    stale = MultimodalGP.load(tmp_path / "kept")
    stale.gp_weights_ = MultimodalGP.load(fast).gp_weights_
    assert np.max(np.abs(stale.nominal_torque(q) - ref)) > 0.1
