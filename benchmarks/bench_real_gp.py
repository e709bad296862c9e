"""Real-robot inverse dynamics: mmgp's GP (make_gp) vs scikit-learn's exact GP vs linear regression.

Data (/work/shared/datasets/ias_nguyen_tuong, read at run time): the published splits of
- real Barrett WAM: 12,000 train / 3,000 test, no overlap;
- real SARCOS: 13,922 train / 5,569 test; the test rows at even indices are exact copies of
  training rows (counted below), so SARCOS figures are also given on the non-duplicated test rows.
Inputs [q, dq, ddq] (21), outputs 7 joint torques. nMSE = MSE / variance of the test targets, per joint.

Models, all on the same split:
- ours: ``make_gp(N)``: above 3,000 samples this is the SGPR ``SparseGP`` (1,000 k-means inducing
  inputs, every training sample used; hyperparameters by the exact-GP LOO objective on a
  1,000-sample random subset);
- the alternative scalable option, "subset of data": an exact ``ExactGP`` conditioned on a random
  3,000-sample subset, same hyperparameters (isolates the predictor; the choice in mmgp/gp/sparse.py
  rests on this comparison), and SGPR with 500 inducing inputs;
- scikit-learn GaussianProcessRegressor, exact, ConstantKernel*RBF(ARD)+WhiteKernel, default
  optimiser, normalize_y=True, one kernel shared by the 7 outputs, on a random subset of
  ``--sk-points`` (default 2,000: on the 2-core machine this ran on, one fit on 2,000 points
  takes ~5 min; 3,000 would take ~3.4x longer);
- scikit-learn LinearRegression on all training rows.

Run: python benchmarks/bench_real_gp.py [--sk-points 2000] [--datasets barrett,sarcos]
"""
from __future__ import annotations

import argparse
import math
import os
import time
import warnings

import numpy as np

ROOT = "/work/shared/datasets/ias_nguyen_tuong"
FILES = {"barrett": "ias_real_barrett_data.mat", "sarcos": "ias_sarcos_data.mat"}


def nmse(pred, Y):
    return ((pred - Y) ** 2).mean(0) / Y.var(0)


def fmt(v):
    return "[" + " ".join(f"{x:.4f}" for x in v) + f"] mean {np.mean(v):.4f}"


def duplicated_test_rows(Xtr, Ytr, Xte, Yte) -> np.ndarray:
    """Boolean (n_test,): test row (inputs and targets) exactly equal to some training row."""
    train = {r.tobytes() for r in np.ascontiguousarray(np.hstack([Xtr, Ytr]))}
    return np.array([r.tobytes() in train for r in np.ascontiguousarray(np.hstack([Xte, Yte]))])


def run(name: str, sk_points: int, seed: int = 0) -> None:
    from scipy.io import loadmat
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
    from sklearn.linear_model import LinearRegression

    from mmgp.gp.exact import ExactGP
    from mmgp.gp.sparse import SparseGP, make_gp

    d = loadmat(os.path.join(ROOT, FILES[name]))
    X, Y, Xt, Yt = d["X_train"], d["Y_train"], d["X_test"], d["Y_test"]
    dup = duplicated_test_rows(X, Y, Xt, Yt)
    print(f"\n=== real {name}: train {X.shape[0]}, test {Xt.shape[0]}, inputs {X.shape[1]}, outputs {Y.shape[1]}; "
          f"test rows that are exact copies of training rows: {dup.sum()}"
          + (f" (even indices: {np.array_equal(np.flatnonzero(dup), np.arange(0, len(Xt), 2))})" if dup.any() else ""),
          flush=True)
    subsets = {"all test rows": np.ones(len(Xt), bool)}
    if dup.any():
        subsets["test rows not in train"] = ~dup
    res = {}

    def report(label, pred, t):
        res[label] = pred
        for sname, mask in subsets.items():
            print(f"{label:>34s} | {sname:>22s} | {t:7.1f} s | nMSE {fmt(nmse(pred[mask], Yt[mask]))}", flush=True)

    t0 = time.perf_counter()
    lin = LinearRegression().fit(X, Y)
    report("linear regression (all rows)", lin.predict(Xt), time.perf_counter() - t0)

    t0 = time.perf_counter()
    ours = make_gp(len(X)).fit(X, Y)
    t_ours = time.perf_counter() - t0
    assert isinstance(ours, SparseGP)
    report(f"ours make_gp -> SGPR M={ours.Z_.shape[0]}", ours.predict(Xt, return_std=False), t_ours)
    _, sd = ours.predict(Xt)
    z = (Yt - res[f"ours make_gp -> SGPR M={ours.Z_.shape[0]}"]) / np.sqrt(sd ** 2 + ours.noise_std_ ** 2)
    print(f"{'':>34s}   calibration: fraction of test torques inside the 95% predictive band "
          f"{np.mean(np.abs(z) < 1.96, 0).round(3).tolist()}")

    t0 = time.perf_counter()
    sp500 = SparseGP(n_inducing=500).fit(X, Y, hyper=ours.hyper_, optimise=False)
    report("SGPR M=500 (same hyper)", sp500.predict(Xt, return_std=False), time.perf_counter() - t0)

    rng = np.random.default_rng(seed)
    sub = np.sort(rng.choice(len(X), 3000, replace=False))
    t0 = time.perf_counter()
    sod = ExactGP().fit(X[sub], Y[sub], hyper=ours.hyper_, optimise=False)
    report("subset-of-data exact 3000 (same hyper)", sod.predict(Xt, return_std=False), time.perf_counter() - t0)

    sub = np.sort(rng.choice(len(X), sk_points, replace=False))
    mu, sdx = X[sub].mean(0), X[sub].std(0)
    k = ConstantKernel(1.0) * RBF(np.full(X.shape[1], max(1.0, math.sqrt(X.shape[1]) / 2))) + WhiteKernel(0.1)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sk = GaussianProcessRegressor(k, n_restarts_optimizer=0, normalize_y=True, random_state=seed)
        sk.fit((X[sub] - mu) / sdx, Y[sub])
    t_sk = time.perf_counter() - t0
    report(f"sklearn exact GP on {sk_points} rows", sk.predict((Xt - mu) / sdx), t_sk)
    print(f"ours vs sklearn: {t_sk / t_ours:.1f}x faster; nMSE ours <= sklearn on "
          f"{int((nmse(res[f'ours make_gp -> SGPR M={ours.Z_.shape[0]}'], Yt) <= nmse(res[f'sklearn exact GP on {sk_points} rows'], Yt)).sum())}/7 joints "
          f"(all test rows); load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sk-points", type=int, default=2000)
    ap.add_argument("--datasets", default="barrett,sarcos")
    a = ap.parse_args()
    for name in a.datasets.split(","):
        run(name, a.sk_points)


if __name__ == "__main__":
    main()
