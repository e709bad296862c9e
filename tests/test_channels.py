"""Dead-band torque channels (mmgp.data.channels) are told to the user by train and diagnose."""
from pathlib import Path

import numpy as np

from mmgp.data.channels import dead_band_warnings

ROOT = Path(__file__).resolve().parents[1]


def _channels(T=2000, seed=0):
    rng = np.random.default_rng(seed)
    smooth = np.sin(np.linspace(0, 20, T)) * 0.4 + rng.normal(scale=0.01, size=T)
    dead = np.where(np.abs(smooth) < 0.3, 0.0, smooth)          # a driver reporting 0 below 0.3
    constant = np.full(T, 2.5)
    return np.c_[smooth, dead, constant]


def test_a_dead_band_is_named_with_its_share_and_size():
    tau = _channels()
    out = dead_band_warnings(tau, ["a", "b", "c"])
    assert len(out) == 1 and out[0].startswith("b: ")
    share = (tau[:, 1] == 0.0).mean()
    assert share > 0.5
    assert f"{100 * share:.0f}% of the samples" in out[0]
    smallest = np.abs(tau[tau[:, 1] != 0, 1]).min()
    assert f"{smallest:.3g} to" in out[0] and smallest >= 0.3


def test_noisy_and_constant_channels_are_not_dead_bands():
    tau = _channels()
    assert dead_band_warnings(tau[:, [0, 2]], ["a", "c"]) == []
    half = tau[:, 1].copy()
    half[: len(half) // 2] = np.linspace(-1, 1, len(half) // 2)   # zeros now on under half the samples
    assert (half == 0.0).mean() < 0.5
    assert dead_band_warnings(half[:, None], ["b"]) == []


def test_train_reports_and_prints_a_dead_band(tmp_path):
    import json

    import pandas as pd
    from typer.testing import CliRunner

    from mmgp.cli import app

    # the shipped replica with its torque passed through a driver's dead band of 0.5 N*m
    log = pd.read_parquet(ROOT / "mmgp/resources/replica/replica_log.parquet")
    tau = log["tau_0"].to_numpy()
    log["tau_0"] = np.where(np.abs(tau) < np.quantile(np.abs(tau), 0.6), 0.0, tau)
    path = tmp_path / "dead.parquet"
    log.to_parquet(path)
    out = tmp_path / "model"
    res = CliRunner().invoke(app, ["train", str(path), "--modes", "1", "--no-disturbance", "--out", str(out),
                                   "--quiet"])
    assert res.exit_code == 0, res.output
    assert "warning: " in res.stderr and "reads exactly 0 on 60% of the samples" in res.stderr
    warnings = json.loads((out / "report.json").read_text())["warnings"]
    assert len(warnings) == 1 and "reads exactly 0 on 60%" in warnings[0]
    # the replica as shipped: no warning
    res = CliRunner().invoke(app, ["train", str(ROOT / "mmgp/resources/replica/replica_log.parquet"), "--modes", "1",
                                   "--no-disturbance", "--out", str(tmp_path / "plain"), "--quiet"])
    assert res.exit_code == 0 and "warning" not in res.stderr
    assert json.loads((tmp_path / "plain" / "report.json").read_text())["warnings"] == []
