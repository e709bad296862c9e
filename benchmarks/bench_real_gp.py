"""Real Barrett WAM and real SARCOS through the commands, against an exact GP on every training
row and against scikit-learn's exact GP.

Must-show of issue 14: ``mmgp convert`` turns /work/shared/datasets/ias_nguyen_tuong into
contract logs (the published train/test splits), then, timed, exactly as a user types them:

    mmgp train  <robot>_train.parquet --modes 1 --no-disturbance --out M
    mmgp predict M <robot>_test.parquet --out P

and the nMSE per joint of P on the published test torques (MSE / variance of the test torques)
is set beside, from the same run:

* **the exact-GP peer**: a float64 exact GP conditioned on *all* training rows (12,000 WAM /
  13,922 SARCOS), one output at a time (one 12,000 x 12,000 kernel is 1.15 GB), on the same
  inputs as ``train`` ([q, dq, ddq, tanh(dq / v_s)]). Its hyperparameters are stated with each
  figure: "ExactGP default" = what ``mmgp.gp.ExactGP().fit(all rows)`` chooses (leave-one-out
  objective on 1,000 random rows after a 300-row coarse climb, the library's standard exact GP),
  and "marginal likelihood" = the textbook/scikit-learn objective on 2,000 random rows;
* **scikit-learn's exact GP** (GaussianProcessRegressor, ConstantKernel * RBF(ARD) +
  WhiteKernel, normalize_y, its L-BFGS on the log marginal likelihood, one kernel for the 7
  outputs, standardised inputs): on all training rows it needs the (N, N, n_hyper) gradient
  tensor, 12,000^2 x 30 x 8 B = 35 GB for the WAM, which this machine (24 GB) cannot hold, so
  it is timed on ``--sk-sizes`` random rows (each fit bounded by ``--sk-limit`` seconds) and its
  O(N^3) scaling is extrapolated to all rows;
* **two cheap peers** (``cheap_peers``): 5-nearest-neighbour regression on standardised
  [q, dq, ddq] (how deterministic the torque is given the inputs) and least squares on
  [1, q, dq, ddq, sin q, cos q].

The published test rows lie along the training trajectory (see ``bench_real_gp_leakfree.py``,
which also runs everything on a leak-free split of contiguous blocks).

Run: ``python benchmarks/bench_real_gp.py [--datasets barrett,sarcos] [--sk-sizes 1000,2000]``
(heavy: ~1 h for both on the shared 2-core machine).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SOURCE = Path("/work/shared/datasets/ias_nguyen_tuong")
PY = [sys.executable, "-m", "mmgp.cli"]


def fmt(v) -> str:
    # three significant digits: on these logs several joints reach nMSE below 1e-4
    return "[" + " ".join(f"{x:.3g}" for x in v) + f"] mean {float(np.mean(v)):.3g}"


def nmse(pred, tau):
    """Normalised MSE per joint (n,): mean squared error / variance of the test torques tau (T, n)."""
    return ((pred - tau) ** 2).mean(0) / tau.var(0)


def command(args: list[str]) -> float:
    """Run ``mmgp ARGS`` in a child process (this checkout first on the path); its wall time."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    t0 = time.perf_counter()
    run = subprocess.run(PY + args, env=env, capture_output=True, text=True)
    if run.returncode != 0:
        raise SystemExit(f"mmgp {' '.join(args)} failed:\n{run.stderr}")
    return time.perf_counter() - t0


def inputs(log, friction_scale):
    from mmgp.labelling.features import StateFeatures

    return StateFeatures("none", friction_scale=friction_scale)(log.q, log.dq, log.ddq, log.tau).X


def exact_peer(X, Y, Xq, hyper_rows: int, objective: str, seed: int = 0):
    """Exact GP on every row of X (N, d) -> Y (N, m), one output at a time (ExactGP's per-output
    mode), hyperparameters by ``objective`` on ``hyper_rows`` random rows; mean at Xq and seconds."""
    from mmgp.gp.exact import ExactGP

    t0 = time.perf_counter()
    fit = ExactGP(objective=objective, max_fit_points=hyper_rows, seed=seed)
    if objective == "loo":
        gp = fit.fit(X, Y)                           # the library's standard exact GP on all rows
    else:
        rng = np.random.default_rng(seed)
        sub = np.sort(rng.choice(len(X), hyper_rows, replace=False))
        hyper = fit.fit(X[sub], Y[sub]).hyper_
        gp = ExactGP(seed=seed, hyper=hyper, optimise=False).fit(X, Y)
    return gp.predict(Xq, return_std=False), time.perf_counter() - t0


def knn_peer(X, Y, Xq, k: int = 5):
    """k-nearest-neighbour regression (scikit-learn, uniform weights) on inputs standardised by
    the training rows: X (N, d) -> Y (N, m), mean at Xq (M, d). How deterministic the torque is
    as a function of the inputs: a small nMSE means near neighbours carry the answer."""
    from sklearn.neighbors import KNeighborsRegressor

    mu, sd = X.mean(0), X.std(0)
    sd[sd == 0] = 1.0
    return KNeighborsRegressor(n_neighbors=k).fit((X - mu) / sd, Y).predict((Xq - mu) / sd)


def linear_peer(q, dq, ddq, Y, qq, dqq, ddqq):
    """Least squares on [1, q, dq, ddq, sin q, cos q] (T, n each) -> Y (T, m), mean at the query
    states: the rigid-body terms are linear in the inertial parameters but not in q, so the
    sines and cosines give it the gravity terms' shape."""
    feats = lambda a, b, c: np.c_[np.ones(len(a)), a, b, c, np.sin(a), np.cos(a)]  # noqa: E731
    coef, *_ = np.linalg.lstsq(feats(q, dq, ddq), Y, rcond=None)
    return feats(qq, dqq, ddqq) @ coef


def cheap_peers(tr, te) -> dict:
    """The 5-nearest-neighbour and linear peers trained on log ``tr``, predicted at log ``te``'s
    states: label -> (T_test, n) N*m."""
    state = lambda log: np.c_[log.q, log.dq, log.ddq]  # noqa: E731
    return {"5-nearest-neighbour (standardised q, dq, ddq)": knn_peer(state(tr), tr.tau, state(te)),
            "linear on [1, q, dq, ddq, sin q, cos q]": linear_peer(tr.q, tr.dq, tr.ddq, tr.tau,
                                                                   te.q, te.dq, te.ddq)}


def sklearn_fit(X, Y, Xq, n: int, limit_s: float, seed: int = 0):
    """scikit-learn's exact GP on ``n`` random rows in a child process killed after ``limit_s``:
    (mean at Xq or None, seconds or None)."""
    import pickle

    rng = np.random.default_rng(seed)
    sub = np.sort(rng.choice(len(X), n, replace=False))
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data.pkl"
        data.write_bytes(pickle.dumps((X[sub], Y[sub], Xq)))
        code = ("import pickle,sys,time,warnings,math,numpy as np\n"
                "from sklearn.gaussian_process import GaussianProcessRegressor as G\n"
                "from sklearn.gaussian_process.kernels import RBF, ConstantKernel as C, WhiteKernel as W\n"
                f"X,Y,Xq=pickle.load(open({str(data)!r},'rb'))\n"
                "mu,sd=X.mean(0),X.std(0); sd[sd==0]=1\n"
                "k=C(1.0)*RBF(np.full(X.shape[1],max(1.0,math.sqrt(X.shape[1])/2)))+W(0.1)\n"
                "t=time.perf_counter()\n"
                "with warnings.catch_warnings():\n warnings.simplefilter('ignore')\n"
                " g=G(k,normalize_y=True,random_state=0).fit((X-mu)/sd,Y)\n"
                "dt=time.perf_counter()-t\n"
                f"pickle.dump((g.predict((Xq-mu)/sd),dt),open({str(Path(tmp) / 'out.pkl')!r},'wb'))\n")
        try:
            subprocess.run([sys.executable, "-c", code], timeout=limit_s, check=True, capture_output=True)
        except subprocess.TimeoutExpired:
            return None, None
        return pickle.loads((Path(tmp) / "out.pkl").read_bytes())


def run_ours(train: Path, test: Path, work: Path, name: str) -> dict:
    """``mmgp train TRAIN --modes 1 --no-disturbance`` then ``mmgp predict``, timed; the logs,
    predicted mean and std (T_test, n) in N*m, the loaded model, its report and the seconds."""
    from mmgp.data.logs import read_log
    from mmgp.estimator import MultimodalGP
    import pandas as pd

    model_dir, pred = work / f"{name}_model", work / f"{name}_pred.parquet"
    t_train = command(["train", str(train), "--modes", "1", "--no-disturbance", "--out", str(model_dir), "--quiet"])
    t_pred = command(["predict", str(model_dir), str(test), "--out", str(pred)])
    tr, te, P = read_log(train), read_log(test), pd.read_parquet(pred)
    n = te.tau.shape[1]
    return dict(tr=tr, te=te, mean=P[[f"tau_hat_{j}" for j in range(n)]].to_numpy(),
                std=P[[f"tau_std_{j}" for j in range(n)]].to_numpy(), model=MultimodalGP.load(model_dir),
                report=json.loads((model_dir / "report.json").read_text()), t_train=t_train, t_pred=t_pred)


def describe_ours(r: dict) -> str:
    """The line that says what ``run_ours`` fitted and how long it took."""
    model, rep = r["model"], r["report"]
    return (f"ours (mmgp train + mmgp predict): GP {model.gp_kinds_[0]} on {len(model.support_Y_[0])} samples, "
            f"hyperparameters on {model.fit_points} random samples, one run per joint; train {r['t_train']:.0f} s "
            f"(fit {rep['timings']['total_s']:.0f} s, {rep['n_sweeps']} EM sweeps), predict {r['t_pred']:.0f} s, "
            f"total {r['t_train'] + r['t_pred']:.0f} s")


def run(name: str, logs: Path, work: Path, sk_sizes: list[int], sk_limit: float, peers: bool = True) -> None:
    r = run_ours(logs / f"ias_{name}_train.parquet", logs / f"ias_{name}_test.parquet", work, name)
    tr, te, ours, model = r["tr"], r["te"], r["mean"], r["model"]
    t_train, t_pred = r["t_train"], r["t_pred"]
    n = te.tau.shape[1]
    nm = lambda p: nmse(p, te.tau)  # noqa: E731
    print(f"\n=== real {name}: train {len(tr.t)} rows, test {len(te.t)} rows, {n} joints")
    print(describe_ours(r))
    cover = np.round((np.abs(ours - te.tau) < 1.96 * r["std"]).mean(0), 3).tolist()
    print(f"  nMSE {fmt(nm(ours))}; 95% band coverage {cover}")
    for label, peer in cheap_peers(tr, te).items():
        print(f"{label}: nMSE {fmt(nm(peer))}; ours <= peer on {int((nm(ours) <= nm(peer)).sum())}/{n} joints")
    X, Xq = inputs(tr, model.friction_scale_), inputs(te, model.friction_scale_)
    for label, rows, obj in (("ExactGP default: LOO on 1,000 random rows", 1000, "loo"),
                             ("marginal likelihood on 2,000 random rows", 2000, "marginal"))[: 2 * peers]:
        peer, t_peer = exact_peer(X, tr.tau, Xq, rows, obj)
        better = int((nm(ours) <= nm(peer)).sum())
        print(f"exact GP on all {len(X)} rows, hyperparameters {label}: {t_peer:.0f} s")
        print(f"  nMSE {fmt(nm(peer))}; ours <= peer on {better}/{n} joints", flush=True)
    times = {}
    for size in sk_sizes:
        mean, secs = sklearn_fit(X, tr.tau, Xq, size, sk_limit)
        if secs is None:
            print(f"scikit-learn exact GP on {size} random rows: not finished in {sk_limit:.0f} s")
            continue
        times[size] = secs
        print(f"scikit-learn exact GP on {size} random rows: fit {secs:.0f} s, nMSE {fmt(nm(mean))}", flush=True)
    if len(times) >= 2:
        a, b = sorted(times)[-2:]
        p = math.log(times[b] / times[a]) / math.log(b / a)
        est = times[b] * (len(X) / b) ** max(p, 3.0)
        print(f"scikit-learn scaling exponent {p:.2f} between {a} and {b} rows; on all {len(X)} rows at least "
              f"~{est / 3600:.1f} h (N^{max(p, 3.0):.1f} from {b} rows), and its (N, N, 30) gradient tensor "
              f"needs {len(X) ** 2 * 30 * 8 / 2 ** 30:.0f} GiB: ours is {est / (t_train + t_pred):.0f}x faster "
              "than that bound")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", default="barrett,sarcos")
    ap.add_argument("--sk-sizes", default="1000,2000")
    ap.add_argument("--sk-limit", type=float, default=1800.0, help="seconds allowed per scikit-learn fit")
    ap.add_argument("--source", default=str(SOURCE), help="the ias_nguyen_tuong folder")
    ap.add_argument("--no-exact-peers", action="store_true", help="skip the exact-GP peers (scikit-learn only)")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        t_conv = command(["convert", a.source, "--out", str(work / "logs")])
        print(f"mmgp convert {a.source} --out DIR: {t_conv:.1f} s")
        for name in a.datasets.split(","):
            run(name, work / "logs", work, [int(s) for s in a.sk_sizes.split(",") if s], a.sk_limit,
                not a.no_exact_peers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
