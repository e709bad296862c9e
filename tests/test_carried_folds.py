"""Held-out blocks over the samples that carry an equation (issue 30): a log that rests most of
the time, poses held between moves, is judged on as many blocks as any other.

The reference for the folds is the plain block split of the carried samples' positions, written
out here; the recording is MuJoCo's (``mmgp.sim.held.held_pose`` with three poses: the UR5 with
2.5 kg on its flange rests 72% of the time, pushed at the holds), diagnosed from the command line.
"""
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from mmgp.cli import app
from mmgp.diagnosis.selection import carried_folds, time_folds
from mmgp.sim.held import HELD, held_pose


def test_blocks_cover_the_carried_samples_once_in_time_order():
    T, K = 400, 5
    t = np.arange(T) / 100.0
    M = np.zeros((T, 2))
    M[50:130, 0] = 1.0      # a move of joint 0
    M[120:160, 1] = 1.0     # overlapping with one of joint 1
    M[300:380, :] = 1.0     # both move
    carried = np.flatnonzero(M.any(1))
    folds = carried_folds(M, K, t, None)
    tests = [te for _, te in folds]
    np.testing.assert_array_equal(np.concatenate(tests), carried)
    # K contiguous runs of the carried positions, sizes as an even split
    edges = np.linspace(0, len(carried), K + 1).round().astype(int)
    for k, te in enumerate(tests):
        np.testing.assert_array_equal(te, carried[edges[k]:edges[k + 1]])
    # training: the other blocks' carried samples, never a resting one
    for tr, te in folds:
        assert set(tr).isdisjoint(te) and set(tr) <= set(carried)
        assert len(carried) - len(te) - 2 * 5 <= len(tr) <= len(carried) - len(te)   # a gap of 0.05 s each side


def test_a_log_that_always_carries_equations_keeps_its_blocks():
    T, K = 300, 4
    t = np.arange(T) / 50.0
    M = np.ones((T, 3))
    M[10:20, 1] = 0.0       # one joint resting while others move: the sample still carries
    for (tr1, te1), (tr2, te2) in zip(carried_folds(M, K, t, 2.0), time_folds(T, K, t, 2.0)):
        np.testing.assert_array_equal(tr1, tr2)
        np.testing.assert_array_equal(te1, te2)


def _diagnosed(cache, tmp_path_factory, seed):
    if seed not in cache:
        d = tmp_path_factory.mktemp(f"three{seed}")
        rec = held_pose(seed=seed, n_poses=3)
        log = d / "held.parquet"
        rec.write(log)
        (d / "fast.yaml").write_text("diagnose:\n  gp: false\n  plots: false\n")
        res = CliRunner().invoke(app, ["diagnose", str(log), "--out", str(d / "out"), "--config",
                                       str(d / "fast.yaml"), "--quiet"])
        assert res.exit_code == 0, res.output
        cache[seed] = rec, json.loads((d / "out" / "findings.json").read_text())
    return cache[seed]


@pytest.fixture(scope="module")
def runs():
    return {}


@pytest.mark.parametrize("seed", [1, 3])
def test_a_payload_held_at_three_poses_is_found(runs, tmp_path_factory, seed):
    _, doc = _diagnosed(runs, tmp_path_factory, seed)
    (pl,) = [f for f in doc["findings"] if f["effect"] == "payload"]
    assert pl["link"] == "wrist_3_link"
    assert pl["params"]["mass"] == pytest.approx(HELD["payload_mass"], rel=0.10)
    assert {f["effect"] for f in doc["findings"]} <= {"payload", "external_disturbance"}


def test_pushes_at_the_held_poses_are_found(runs, tmp_path_factory):
    # every push of seed 3 is at a hold, where the scan reads the torque beyond the friction
    # band (separation.hold_interiors); nothing is reported away from a push
    rec, doc = _diagnosed(runs, tmp_path_factory, 3)
    (dist,) = [f for f in doc["findings"] if f["effect"] == "external_disturbance"]
    spans, truth = dist["params"]["spans_s"], rec.info["push_spans"]
    for a, b in truth:
        overlap = sum(min(e, b) - max(s, a) for s, e in spans if s < b and e > a)
        assert overlap > 0.8 * (b - a), (a, b, spans)
    assert all(any(s < b + 0.3 and e > a - 0.3 for a, b in truth) for s, e in spans)
