"""Real Barrett WAM and real SARCOS on a leak-free split (issue 31 item 9): ours against a
5-nearest-neighbour, a linear and the exact-GP peer, and the same cheap peers on the published
split for the ratio.

What the published files are (checked on every run, printed): each set's train and test files
are *one* time-ordered recording sampled twice. The WAM's 15,000 samples were split every 5th to
test (test row j lies between training rows 4j-1 and 4j, their midpoint to 0.005 standardised
units); SARCOS's training file is every 2nd sample and its test file every 5th (test row 2k is
training row 5k, an exact copy; test row 2k+1 lies between training rows 5k+2 and 5k+3). So every
published test row has training rows a fraction of a sample away in time, and the published
figures measure interpolation along the training trajectory.

The split here: both files pooled in recording order (a row's position is its fraction of its
own file; test rows that are exact copies of training rows, inputs and torques within ``--tol``,
are one sample and kept once), cut into ``--blocks`` contiguous blocks of equal length; every
``--test-every``-th block is test (10 and 5: blocks 5 and 10, 20% of the rows), the others are
training. From the test blocks, every row within ``--tol`` (Euclidean, on q, dq, ddq) of any
training row is dropped. ``--max-train`` caps training as contiguous pieces too: the first
``max_train // n_training_blocks`` rows of each training block (what ours, the exact GP and the
"same rows" peers learn from); the cheap peers also learn from every training row.

Run: ``python benchmarks/bench_real_gp_leakfree.py --datasets barrett --max-train 4000``
(one dataset ~10 min on the shared 2-core machine).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real_gp import (REPO, SOURCE, cheap_peers, command, exact_peer, fmt, inputs,  # noqa: E402
                           nmse, run_ours, describe_ours)


def state(log) -> np.ndarray:
    """The model's state inputs [q, dq, ddq] (T, 3n) of a log."""
    return np.c_[log.q, log.dq, log.ddq]


def pool_in_time(tr, te, tol: float) -> tuple[dict, dict]:
    """Published train and test logs as one recording: arrays q, dq, ddq, tau (M, n) in recording
    order, and the checks behind that order (printed by the caller)."""
    from scipy.spatial import cKDTree

    both = lambda log: np.c_[state(log), log.tau]  # noqa: E731
    dist, _ = cKDTree(both(tr)).query(both(te), distance_upper_bound=tol)
    copy = np.isfinite(dist)                        # the same sample in both files
    pos = np.r_[np.arange(len(tr.t)) / len(tr.t), np.arange(len(te.t))[~copy] / len(te.t)]
    origin = np.r_[np.zeros(len(tr.t), int), np.ones(int((~copy).sum()), int)]
    order = np.lexsort((-origin, pos))             # a tie: the test row came first (WAM: 5j before 4j)
    pick = lambda a, b: np.r_[a, b[~copy]][order]  # noqa: E731
    pooled = {k: pick(getattr(tr, k), getattr(te, k)) for k in ("q", "dq", "ddq", "tau")}
    # Check of the order: the training row nearest (in standardised q) to each test row should be
    # the one at the test row's fraction of the recording.
    mu, sd = tr.q.mean(0), tr.q.std(0)
    _, near = cKDTree((tr.q - mu) / sd).query((te.q - mu) / sd)
    off = near - np.arange(len(te.t)) * len(tr.t) / len(te.t)
    step = lambda q: np.median(np.abs(np.diff(q, axis=0)).max(1))  # noqa: E731
    checks = dict(copies=int(copy.sum()), within2=float((np.abs(off) <= 2).mean()),
                  median_off=float(np.median(np.abs(off))), step_ratio=step(te.q) / step(tr.q))
    return pooled, checks


def leak_free_split(M: int, blocks: int, test_every: int, max_train: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row indices into the pooled recording (M rows): training (all), training (capped) and test.
    Blocks are contiguous and of equal length; block b is test when (b + 1) % test_every == 0."""
    block = np.arange(M) * blocks // M
    test = (block + 1) % test_every == 0
    train = np.flatnonzero(~test)
    train_blocks = np.unique(block[train])
    per = max_train // len(train_blocks) if max_train else M
    capped = np.concatenate([np.flatnonzero(block == b)[:per] for b in train_blocks])
    return train, capped, np.flatnonzero(test)


def near_rows(X_train: np.ndarray, X_test: np.ndarray, tol: float) -> np.ndarray:
    """(M_test,) bool: test rows within ``tol`` (Euclidean) of any training row."""
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(X_train).query(X_test, distance_upper_bound=tol)
    return np.isfinite(dist)


def nearest_distance(X_train: np.ndarray, X_test: np.ndarray) -> float:
    """Median distance of a test row to its nearest training row, inputs standardised by the
    training rows: how far the test set is from what was learnt."""
    from scipy.spatial import cKDTree

    mu, sd = X_train.mean(0), X_train.std(0)
    return float(np.median(cKDTree((X_train - mu) / sd).query((X_test - mu) / sd)[0]))


def hyper_line(h) -> str:
    """Per joint noise / signal variance and the shortest lengthscale (standardised inputs) of a
    ``Hyper``: what the GP will do away from its rows (tiny noise and short lengthscales
    interpolate the training trajectory; off it the mean can swing far from the data)."""
    return (f"noise/signal {np.array2string(h.noise_var / h.signal_var, precision=2)}, shortest lengthscale "
            f"{np.array2string(h.lengthscale.min(1), precision=2)}")


def write_part(path: Path, pooled: dict, rows: np.ndarray, dt: float) -> Path:
    """Rows of the pooled recording as a contract log; ``t`` = recording position * dt (s), so
    gaps between blocks stay gaps."""
    from mmgp.data.logs import write_log

    return write_log(path, rows * dt, pooled["q"][rows], pooled["tau"][rows], dq=pooled["dq"][rows],
                     ddq=pooled["ddq"][rows])


def make_split(name: str, logs: Path, work: Path, a) -> dict:
    """Pool, split, drop near rows, write the two logs; print what was found; the published logs,
    the pooled recording and the paths."""
    from mmgp.convert.datasets.mat_sets import estimate_row_spacing
    from mmgp.data.logs import read_log

    pub_tr, pub_te = (read_log(logs / f"ias_{name}_{s}.parquet") for s in ("train", "test"))
    pooled, c = pool_in_time(pub_tr, pub_te, a.tol)
    M = len(pooled["q"])
    train, capped, test = leak_free_split(M, a.blocks, a.test_every, a.max_train)
    near = near_rows(np.c_[pooled["q"], pooled["dq"], pooled["ddq"]][train],
                     np.c_[pooled["q"], pooled["dq"], pooled["ddq"]][test], a.tol)
    dt = estimate_row_spacing(pooled["q"], pooled["dq"])
    paths = {k: write_part(work / f"{name}_leakfree_{k}.parquet", pooled, rows, dt)
             for k, rows in (("train_all", train), ("train", capped), ("test", test[~near]))}
    print(f"\n=== real {name}: published train {len(pub_tr.t)} rows, test {len(pub_te.t)} rows")
    print(f"recording order: published test rows that are exact copies of training rows (inputs and "
          f"torques within {a.tol:g}): {c['copies']}; the files step {c['step_ratio']:.2f}x apart "
          f"(median max |dq| per row, test / train); nearest training row (standardised q) of test row j "
          f"within 2 rows of j * {len(pub_tr.t)}/{len(pub_te.t)}: {100 * c['within2']:.1f}% "
          f"(median offset {c['median_off']:.2f} rows)")
    print(f"leak-free split: {M} pooled rows in {a.blocks} contiguous blocks, test = blocks "
          f"{list(range(a.test_every, a.blocks + 1, a.test_every))} of 1..{a.blocks} ({len(test)} rows); "
          f"{int(near.sum())} test rows within {a.tol:g} of a training row dropped -> test {int((~near).sum())} rows; "
          f"training {len(train)} rows, capped to {len(capped)} "
          f"(the first {len(capped) // (a.blocks - a.blocks // a.test_every)} rows of each training block); "
          f"t = position * {dt:.5f} s")
    return dict(pub_tr=pub_tr, pub_te=pub_te, paths=paths)


def run(name: str, logs: Path, work: Path, a) -> None:
    from mmgp.data.logs import read_log

    s = make_split(name, logs, work, a)
    r = run_ours(s["paths"]["train"], s["paths"]["test"], work, f"{name}_leakfree")
    tr, te, full = r["tr"], r["te"], read_log(s["paths"]["train_all"])
    mine = nmse(r["mean"], te.tau)
    n = len(mine)
    print(f"median standardised distance test -> nearest training row (q, dq, ddq): published "
          f"{nearest_distance(state(s['pub_tr']), state(s['pub_te'])):.3f}, leak-free "
          f"{nearest_distance(state(full), state(te)):.3f}")
    print(f"\nleak-free split, training on the same {len(tr.t)} rows as ours:")
    print(describe_ours(r))
    cover = np.round((np.abs(r["mean"] - te.tau) < 1.96 * r["std"]).mean(0), 3).tolist()
    print(f"  nMSE {fmt(mine)}; 95% band coverage {cover}; {hyper_line(r['model'].hypers_[0])}")
    rows = [(f"{k} on the same {len(tr.t)} rows", v) for k, v in cheap_peers(tr, te).items()]
    if a.exact_peer:
        X, Xq = inputs(tr, r["model"].friction_scale_), inputs(te, r["model"].friction_scale_)
        peer, secs = exact_peer(X, tr.tau, Xq, 1000, "loo")
        rows.append((f"exact GP on the same {len(tr.t)} rows, ExactGP default (LOO on 1,000 rows; {secs:.0f} s)", peer))
    rows += [(f"{k} on all {len(full.t)} training rows", v) for k, v in cheap_peers(full, te).items()]
    for label, peer in rows:
        print(f"{label}: nMSE {fmt(nmse(peer, te.tau))}; ours <= peer on "
              f"{int((mine <= nmse(peer, te.tau)).sum())}/{n} joints", flush=True)
    print(f"\npublished split (train {len(s['pub_tr'].t)} rows, test {len(s['pub_te'].t)} rows), the cheap "
          "peers for the ratio:")
    full_peers = cheap_peers(full, te)
    for label, peer in cheap_peers(s["pub_tr"], s["pub_te"]).items():
        pub = nmse(peer, s["pub_te"].tau)
        ratio = float(np.mean(nmse(full_peers[label], te.tau)) / np.mean(pub))
        print(f"{label}: nMSE {fmt(pub)}; leak-free (all training rows) / published mean: {ratio:.1f}x")
    import os

    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", default="barrett,sarcos")
    ap.add_argument("--source", default=str(SOURCE), help="the ias_nguyen_tuong folder")
    ap.add_argument("--blocks", type=int, default=10, help="contiguous blocks of the pooled recording")
    ap.add_argument("--test-every", type=int, default=5, help="every k-th block is test")
    ap.add_argument("--max-train", type=int, default=4000, help="training rows for ours and the exact GP (0: all)")
    ap.add_argument("--tol", type=float, default=1e-9, help="distance under which two rows are the same")
    ap.add_argument("--no-exact-peer", dest="exact_peer", action="store_false", help="skip the exact-GP peer")
    a = ap.parse_args(argv)
    if a.blocks < 2 or not 2 <= a.test_every <= a.blocks or a.max_train < 0 or a.tol < 0:
        ap.error("need --blocks >= 2, 2 <= --test-every <= --blocks, --max-train >= 0, --tol >= 0")
    sys.path.insert(0, str(REPO))
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        command(["convert", a.source, "--out", str(work / "logs")])
        for name in a.datasets.split(","):
            run(name, work / "logs", work, a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
