"""Training that scales (issue 14): the thread policy, the default device, the per-output exact
GP, the chunked SGPR, the size rule of make_gp, the EM-free single-mode fit, model format v3,
and commands that clean up after SIGTERM. References are closed forms in numpy."""
from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
import torch

import mmgp.gp.exact as exact_mod
import mmgp.gp.sparse as sparse_mod
import mmgp.threads as threads
from mmgp.gp.exact import ExactGP
from mmgp.gp.hyper import Hyper
from mmgp.gp.linalg import default_device, resolve_device
from mmgp.gp.sparse import SparseGP, choose_gp_method, make_gp


def toy(N=80, m=2, seed=0, noise=0.05):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (N, 2))
    Y = np.stack([np.sin(X[:, 0]) + 0.5 * X[:, 1], np.cos(X[:, 1]) * X[:, 0]][:m], 1)
    return X, Y + noise * rng.standard_normal(Y.shape)


def numpy_gp(gp, X, Y, Xq):
    """Textbook exact GP mean, std (with noise) and LOO, per output, in the GP's standardised
    units mapped back to data units."""
    xs, ys, h = gp.x_scaler_, gp.y_scaler_, gp.hyper_
    A, B = xs.transform(X), xs.transform(Xq)
    out = {"mean": [], "std": [], "loo_mean": [], "loo_std": []}
    for j in range(Y.shape[1]):
        def k(P, Q, j=j):
            return h.signal_var[j] * np.exp(-0.5 * (((P[:, None] - Q[None]) / h.lengthscale[j]) ** 2).sum(-1))

        K = k(A, A) + h.noise_var[j] * np.eye(len(A))
        y = (Y[:, j] - ys.mean_[j]) / ys.scale_[j]
        Ks = k(A, B)
        out["mean"].append(Ks.T @ np.linalg.solve(K, y) * ys.scale_[j] + ys.mean_[j])
        var = h.signal_var[j] + h.noise_var[j] - np.einsum("ij,ij->j", Ks, np.linalg.solve(K, Ks))
        out["std"].append(np.sqrt(var) * ys.scale_[j])
        P = np.linalg.inv(K)
        out["loo_mean"].append((y - P @ y / np.diag(P)) * ys.scale_[j] + ys.mean_[j])
        out["loo_std"].append(np.sqrt(1.0 / np.diag(P)) * ys.scale_[j])
    return {key: np.stack(v, 1) for key, v in out.items()}


# ------------------------------------------------------------------------------- thread policy
@pytest.mark.parametrize("cores,load,cap,rows,device,expected", [
    (16, 0.0, "", 10000, "cpu", 16),       # idle machine, large matrix: every core
    (16, 10.0, "", 10000, "cpu", 7),       # 16 - 10 busy + this process's own core
    (2, 7.0, "", 10000, "cpu", 1),         # the shared development machine
    (16, 0.0, "4", 10000, "cpu", 4),       # OMP_NUM_THREADS caps it
    (16, 0.0, "", 500, "cpu", 1),          # small factorisations: one thread
    (16, 0.0, "", 10000, "cuda", 1),       # on a GPU the CPU only does bookkeeping
])
def test_threads_for_follows_the_policy(monkeypatch, cores, load, cap, rows, device, expected):
    monkeypatch.setattr(threads, "usable_cores", lambda: cores)
    monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))
    monkeypatch.setenv("OMP_NUM_THREADS", cap)
    assert threads.threads_for(rows, device) == expected


def test_limit_threads_sets_torch_and_blas_pools_and_restores_them():
    from threadpoolctl import threadpool_info

    before = torch.get_num_threads()
    with threads.limit_threads(1):
        assert torch.get_num_threads() == 1
        assert all(p["num_threads"] == 1 for p in threadpool_info())
        with threads.limit_threads(2):
            assert torch.get_num_threads() == 2
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


def test_limit_threads_blas_only_leaves_torch_and_openmp_alone():
    from threadpoolctl import threadpool_info

    before = torch.get_num_threads()
    pools = {p["filepath"]: p["num_threads"] for p in threadpool_info()}
    with threads.limit_threads(1, blas_only=True):
        assert torch.get_num_threads() == before
        for p in threadpool_info():
            assert p["num_threads"] == (1 if p["user_api"] == "blas" else pools[p["filepath"]])
    assert {p["filepath"]: p["num_threads"] for p in threadpool_info()} == pools


def test_compare_runs_its_folds_on_one_thread(monkeypatch):
    import mmgp.evaluation.compare as compare_mod
    from mmgp.data.logs import RobotLog

    seen = []
    real = compare_mod._fit_gp

    def spy(*a, **k):
        seen.append(torch.get_num_threads())
        return real(*a, **k)

    monkeypatch.setattr(compare_mod, "_fit_gp", spy)
    t = np.arange(300) * 0.01
    q = np.sin(t)[:, None]
    log = RobotLog(path="<arrays>", t=t, q=q, tau=2 * q, dq=np.cos(t)[:, None], ddq=-q)
    with threads.limit_threads(2):
        compare_mod.compare(log, None, n_folds=2, gap=5, max_train=60, gp_options={"max_iter": 5})
        assert torch.get_num_threads() == 2
    assert seen and set(seen) == {1}


# ------------------------------------------------------------------------------- device plumbing
def test_default_device_reaches_gps_built_without_one():
    X, Y = toy(N=30)
    hyp = Hyper(np.full((2, 2), 0.8), np.ones(2), np.full(2, 0.05))
    with default_device("cpu"):
        assert ExactGP(hyper=hyp, optimise=False).fit(X, Y).dev_ == torch.device("cpu")
    assert resolve_device(None) == torch.device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            with default_device("cuda"):
                pass
        with pytest.raises(ValueError, match="no CUDA device"):
            ExactGP(device="cuda", hyper=hyp, optimise=False).fit(X, Y)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without a GPU")
@pytest.mark.parametrize("argv", [["train", "{log}", "--out", "{out}", "--device", "cuda"],
                                  ["diagnose", "{log}", "--out", "{out}", "--device", "cuda"],
                                  ["compare", "{log}", "--out", "{out}", "--device", "cuda"]])
def test_device_cuda_without_gpu_is_one_clear_error(tmp_path, argv):
    from typer.testing import CliRunner

    from mmgp.cli import app
    from mmgp.resources import demo_files

    log, _ = demo_files()
    out = tmp_path / "out"
    res = CliRunner().invoke(app, [a.format(log=log, out=out) for a in argv])
    assert res.exit_code == 2, res.output
    assert "cuda" in res.output and "no CUDA device" in res.output
    assert not out.exists() and not list(tmp_path.glob(".out.partial*"))


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without a GPU")
def test_predict_with_a_cuda_model_on_a_cpu_machine_names_the_way_out(tmp_path):
    import json

    from typer.testing import CliRunner

    from mmgp import MultimodalGP
    from mmgp.cli import app
    from mmgp.data.logs import read_log
    from mmgp.resources import demo_files

    log, _ = demo_files()
    lg = read_log(log)
    MultimodalGP(n_modes=1, disturbance=False, fit_iter=5).fit(log).save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    meta["settings"]["device"] = "cuda"                 # as written by 'mmgp train --device cuda'
    (tmp_path / "m" / "model.json").write_text(json.dumps(meta))
    runner = CliRunner()
    res = runner.invoke(app, ["predict", str(tmp_path / "m"), str(log), "--out", str(tmp_path / "p.parquet")])
    assert res.exit_code == 2 and "--device cpu" in res.output
    res = runner.invoke(app, ["predict", str(tmp_path / "m"), str(log), "--out", str(tmp_path / "p.parquet"),
                              "--device", "cpu"])
    assert res.exit_code == 0, res.output
    import pandas as pd

    assert len(pd.read_parquet(tmp_path / "p.parquet")) == lg.n_samples


# ------------------------------------------------------------------------------- GPs
def test_per_output_exact_gp_matches_the_closed_form(monkeypatch):
    monkeypatch.setattr(exact_mod, "BATCHED_BYTES", 0)        # force one output at a time
    X, Y = toy(N=70)
    Xq = toy(N=15, seed=3)[0]
    hyp = Hyper(np.array([[0.7, 1.1], [1.3, 0.6]]), np.array([1.2, 0.8]), np.array([0.04, 0.02]))
    gp = ExactGP(hyper=hyp, optimise=False).fit(X, Y)
    assert gp.per_output_ and gp.L_ is None
    ref = numpy_gp(gp, X, Y, Xq)
    mean_only = gp.predict(Xq, return_std=False)             # no factorisation needed for the mean...
    mean, std = gp.predict(Xq, include_noise=True)
    np.testing.assert_allclose(mean_only, ref["mean"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(mean, ref["mean"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(std, ref["std"], rtol=1e-8)
    lm, ls = gp.loo_predictive()
    np.testing.assert_allclose(lm, ref["loo_mean"], rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(ls, ref["loo_std"], rtol=1e-8)


def test_chunked_sgpr_matches_dense_formulas(monkeypatch):
    monkeypatch.setattr(sparse_mod, "CHUNK_BYTES", 8 * 12 * 64)   # 64-sample chunks: 5 of them
    X, Y = toy(N=300, m=1)
    y = Y[:, 0]
    hyp = Hyper(np.array([[0.9, 1.4]]), np.array([1.3]), np.array([0.03]))
    sp = SparseGP(n_inducing=12, hyper=hyp, optimise=False).fit(X, y)
    Xs, Z = sp.x_scaler_.transform(X), sp.Z_
    ys = (y - sp.y_scaler_.mean_[0]) / sp.y_scaler_.scale_[0]
    k = lambda A, B: 1.3 * np.exp(-0.5 * (((A[:, None] - B[None]) / hyp.lengthscale[0]) ** 2).sum(-1))  # noqa: E731
    Kuu, Kuf = k(Z, Z), k(Z, Xs)
    Sigma = np.linalg.inv(Kuu + Kuf @ Kuf.T / 0.03)
    Xq = X[:10] * 0.9
    Ksu = k(sp.x_scaler_.transform(Xq), Z)
    sc = sp.y_scaler_.scale_[0]
    np.testing.assert_allclose(sp.predict(Xq, return_std=False), (Ksu @ Sigma @ Kuf @ ys / 0.03) * sc
                               + sp.y_scaler_.mean_[0], rtol=1e-7, atol=1e-7 * sc)
    # DTC LOO: (Qff + s2 I)^-1 in closed form
    C = Kuf.T @ np.linalg.solve(Kuu, Kuf) + 0.03 * np.eye(len(X))
    P = np.linalg.inv(C)
    lm, lsd = sp.loo_predictive()
    np.testing.assert_allclose(lm, (ys - P @ ys / np.diag(P)) * sc + sp.y_scaler_.mean_[0], rtol=1e-6, atol=1e-6 * sc)
    np.testing.assert_allclose(lsd, np.sqrt(1.0 / np.diag(P)) * sc, rtol=1e-6)
    # inducing inputs given back in data units reproduce the same model
    twin = SparseGP(n_inducing=12, hyper=hyp, optimise=False).fit(X, y, inducing=sp.inducing_)
    np.testing.assert_allclose(twin.predict(Xq)[1], sp.predict(Xq)[1], rtol=1e-10)


def test_make_gp_rule_exact_while_memory_allows_then_sgpr(monkeypatch):
    assert choose_gp_method(12000) == "exact"
    assert choose_gp_method(sparse_mod.EXACT_MAX_SAMPLES + 1) == "sgpr"
    assert choose_gp_method(100, "subset") == "subset"
    monkeypatch.setattr("mmgp.gp.linalg.memory_budget", lambda dev: 3 * 8 * 1000 ** 2)
    assert choose_gp_method(1000) == "exact" and choose_gp_method(1001) == "sgpr"
    assert type(make_gp(1001, n_inducing=10)) is SparseGP
    with pytest.raises(ValueError, match="auto, exact, sgpr, subset"):
        choose_gp_method(10, "dense")


def test_independent_outputs_are_each_optimised_alone():
    from mmgp.gp.hyper import default_hyper, optimise_hyper

    X, Y = toy(N=60)
    Xs = torch.as_tensor((X - X.mean(0)) / X.std(0))
    Ys = torch.as_tensor((Y - Y.mean(0)) / Y.std(0))
    init = default_hyper(2, 2)
    both, value = optimise_hyper(Xs, Ys, init, max_iter=15, independent=True)
    alone = [optimise_hyper(Xs, Ys[:, j:j + 1], init.output(j), max_iter=15) for j in range(2)]
    for j, (h, _) in enumerate(alone):
        np.testing.assert_allclose(both.lengthscale[j], h.lengthscale[0], rtol=1e-12)
        assert both.noise_var[j] == pytest.approx(h.noise_var[0], rel=1e-12)
    assert value == pytest.approx(sum(v for _, v in alone), rel=1e-12)


# ------------------------------------------------------------------------------- the estimator
def replica_arrays(T=400, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * 0.05
    q = np.stack([np.sin(0.7 * t), np.cos(0.4 * t)], 1)
    tau = np.stack([3 * np.sin(q[:, 0]) + q[:, 1], np.cos(q[:, 1]) * 2], 1) + 0.02 * rng.standard_normal((T, 2))
    return t, q, tau


def test_one_mode_without_disturbance_skips_the_em_and_uses_every_sample():
    from mmgp import MultimodalGP

    t, q, tau = replica_arrays()
    model = MultimodalGP(n_modes=1, disturbance=False, fit_iter=15).fit(t=t, q=q, tau=tau)
    sem = model.sem_
    assert sem.n_sweeps_ == 0 and sem.trace_ == [] and model.report_["likelihood_trace"] == []
    assert (model.labels_["mode"] == 0).all() and (model.labels_["disturbed"] == 0).all()
    assert len(model.support_Y_[0]) == len(t) and model.gp_kinds_ == ["exact"]
    # predictions are the exact GP on every sample with the learned hyperparameters
    gp = model.gp(0)
    X = model.features_.X
    Xq = X[::37] + 0.01
    ref = numpy_gp(gp, X, model.features_.Y, Xq)
    mean, std = gp.predict(Xq, include_noise=True)
    np.testing.assert_allclose(mean, ref["mean"], rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(std, ref["std"], rtol=1e-6)


def test_sgpr_model_round_trips_through_save_and_load(tmp_path):
    from mmgp import MultimodalGP

    t, q, tau = replica_arrays(T=300)
    model = MultimodalGP(n_modes=1, disturbance=False, gp_method="sgpr", n_inducing=40, fit_iter=10)
    model.fit(t=t, q=q, tau=tau)
    assert model.gp_kinds_ == ["sgpr"] and model.inducing_[0].shape[0] <= 40
    model.save(tmp_path / "m")
    back = MultimodalGP.load(tmp_path / "m")
    assert back.gp_kinds_ == ["sgpr"]
    dq, ddq = np.gradient(q, t, axis=0), np.gradient(np.gradient(q, t, axis=0), t, axis=0)
    for a, b in zip(model.predict(q[::11], dq[::11], ddq[::11]), back.predict(q[::11], dq[::11], ddq[::11])):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-10)


def test_several_modes_still_run_the_em():
    from mmgp import MultimodalGP

    t, q, tau = replica_arrays(T=300)
    model = MultimodalGP(n_modes=1, disturbance=True, max_sweeps=3, min_sweeps=2, average_last=1,
                         fit_iter=5).fit(t=t, q=q, tau=tau)
    assert model.sem_.n_sweeps_ >= 2 and len(model.report_["likelihood_trace"]) >= 3


# ------------------------------------------------------------------------------- interrupted commands
def test_sigterm_inside_a_command_removes_its_unfinished_output(tmp_path):
    from mmgp.cli.common import command_numerics
    from mmgp.data.outputs import atomic_output_dir

    out = tmp_path / "out"
    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stop:
        with command_numerics(None), atomic_output_dir(out) as tmp:
            (tmp / "half.txt").write_text("unfinished")
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)            # the handler interrupts this
    assert stop.value.code == 128 + signal.SIGTERM
    assert not out.exists() and list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is previous
