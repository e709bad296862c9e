"""Classification and regression figures (mmgp.evaluate) against hand counts and closed forms."""
from __future__ import annotations

from itertools import permutations
from math import comb

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import adjusted_rand_score

from mmgp.evaluation.metrics import SOURCE_FIGURES, classification_figures, format_figures, normalised_mse


def frames(d_true, d_pred, m_true=None, m_pred=None):
    T = len(d_true)
    t = 0.05 * np.arange(T)
    truth = pd.DataFrame({"t": t, "disturbed": d_true})
    pred = pd.DataFrame({"t": t, "disturbed": d_pred, "mode": m_pred if m_pred is not None else np.zeros(T, int)})
    if m_true is not None:
        truth["mode"] = m_true
    return pred, truth


def test_hand_counted_confusion_with_ambiguous_samples():
    #            0  1  2  3  4  5  6  7  8  9 10 11
    d_true = [0, 0, 0, 0, 0, 1, 1, 1, -1, -1, -1, 0]
    d_pred = [0, 0, 1, 0, 0, 1, 0, 1, 1, 0, 1, 1]
    # judged: 9 (rows 8-10 left out). Truly undisturbed: rows 0-4, 11 -> 6, called 0: rows 0,1,3,4 -> 4.
    # Truly disturbed: rows 5-7 -> 3, missed: row 6 -> 1. TP = 2, FP = 2 (rows 2, 11), FN = 1, TN = 4.
    f = classification_figures(*frames(np.array(d_true), np.array(d_pred)))
    assert f["n_samples"] == 12
    assert f["n_ambiguous_left_out"] == 3
    assert f["n_judged"] == 9
    assert f["n_unperturbed"] == 6 and f["n_perturbed"] == 3
    assert f["accuracy"] == pytest.approx(6 / 9, abs=1e-15)
    assert f["unperturbed_correct"] == pytest.approx(4 / 6, abs=1e-15)
    assert f["perturbed_missed"] == pytest.approx(1 / 3, abs=1e-15)
    assert f["disturbed_precision"] == pytest.approx(2 / 4, abs=1e-15)
    assert f["disturbed_recall"] == pytest.approx(2 / 3, abs=1e-15)
    assert f["disturbed_f1"] == pytest.approx(2 * 2 / (2 * 2 + 2 + 1), abs=1e-15)  # 2TP / (2TP + FP + FN)


def test_random_confusion_against_loop_counts():
    rng = np.random.default_rng(0)
    T = 500
    d_true = rng.choice([-1, 0, 1], T, p=[0.1, 0.6, 0.3])
    d_pred = np.where(rng.random(T) < 0.8, np.abs(d_true), 1 - np.abs(d_true))
    tp = fp = tn = fn = amb = 0
    for a, b in zip(d_true, d_pred):
        if a == -1:
            amb += 1
        elif a == 1 and b == 1:
            tp += 1
        elif a == 1:
            fn += 1
        elif b == 1:
            fp += 1
        else:
            tn += 1
    f = classification_figures(*frames(d_true, d_pred))
    assert f["n_ambiguous_left_out"] == amb and f["n_judged"] == T - amb
    assert f["accuracy"] == pytest.approx((tp + tn) / (T - amb), abs=1e-14)
    assert f["unperturbed_correct"] == pytest.approx(tn / (tn + fp), abs=1e-14)
    assert f["perturbed_missed"] == pytest.approx(fn / (tp + fn), abs=1e-14)
    assert f["disturbed_precision"] == pytest.approx(tp / (tp + fp), abs=1e-14)
    assert f["disturbed_recall"] == pytest.approx(tp / (tp + fn), abs=1e-14)
    assert f["disturbed_f1"] == pytest.approx(2 * tp / (2 * tp + fp + fn), abs=1e-14)


def test_source_figures_reproduced_from_counts():
    # 192 of 235 unperturbed correct, 14 of 92 perturbed missed (Haninger 2016).
    d_true = np.r_[np.zeros(235, int), np.ones(92, int)]
    d_pred = np.r_[np.zeros(192, int), np.ones(43, int), np.zeros(14, int), np.ones(78, int)]
    f = classification_figures(*frames(d_true, d_pred))
    assert f["unperturbed_correct"] == pytest.approx(SOURCE_FIGURES["unperturbed_correct"], abs=1e-15)
    assert f["perturbed_missed"] == pytest.approx(SOURCE_FIGURES["perturbed_missed"], abs=1e-15)
    text = format_figures(f, with_source=True)
    assert "327" in text and text.count("0.817") == 2 and text.count("0.152") == 2  # ours and the source's


def ari_reference(a, b):
    """Hubert & Arabie's adjusted Rand index from the contingency table."""
    ca, cb = np.unique(a, return_inverse=True)[1], np.unique(b, return_inverse=True)[1]
    table = np.zeros((ca.max() + 1, cb.max() + 1), int)
    np.add.at(table, (ca, cb), 1)
    index = sum(comb(int(v), 2) for v in table.ravel())
    sa = sum(comb(int(v), 2) for v in table.sum(1))
    sb = sum(comb(int(v), 2) for v in table.sum(0))
    expected = sa * sb / comb(len(a), 2)
    return (index - expected) / (0.5 * (sa + sb) - expected)


def test_mode_ari_is_permutation_invariant_and_leaves_out_ambiguous():
    rng = np.random.default_rng(1)
    T = 300
    m_true = np.repeat(rng.integers(0, 3, 30), 10)
    d_true = rng.choice([-1, 0, 1], T, p=[0.15, 0.7, 0.15])
    d_pred = (d_true == 1).astype(int)
    for perm in permutations(range(3)):
        m_pred = np.array(perm)[m_true]
        f = classification_figures(*frames(d_true, d_pred, m_true, m_pred))
        assert f["mode_adjusted_rand_index"] == pytest.approx(1.0, abs=1e-12)
    # Scramble 20% of the predicted modes, and make the ambiguous samples all wrong: they must
    # not count.
    m_pred = np.array([2, 0, 1])[m_true]
    flip = rng.random(T) < 0.2
    m_pred[flip] = rng.integers(0, 3, flip.sum())
    m_pred[d_true == -1] = 7
    keep = d_true != -1
    f = classification_figures(*frames(d_true, d_pred, m_true, m_pred))
    ref = ari_reference(m_true[keep], m_pred[keep])
    assert f["mode_adjusted_rand_index"] == pytest.approx(ref, abs=1e-12)
    assert f["mode_adjusted_rand_index"] == pytest.approx(adjusted_rand_score(m_true[keep], m_pred[keep]), abs=1e-12)
    assert f["mode_adjusted_rand_index"] < 0.9


def test_modes_only_truth():
    rng = np.random.default_rng(2)
    m_true = rng.integers(0, 2, 50)
    m_pred = np.where(rng.random(50) < 0.9, m_true, 1 - m_true)
    pred = pd.DataFrame({"t": np.arange(50.0), "mode": m_pred, "disturbed": np.zeros(50, int)})
    truth = pd.DataFrame({"t": np.arange(50.0), "mode": m_true})
    f = classification_figures(pred, truth)
    assert f["n_ambiguous_left_out"] == 0 and f["n_judged"] == 50
    assert "accuracy" not in f
    assert f["mode_adjusted_rand_index"] == pytest.approx(ari_reference(m_true, m_pred), abs=1e-12)


def test_misaligned_frames_are_refused():
    pred, truth = frames(np.zeros(5, int), np.zeros(5, int))
    with pytest.raises(ValueError):
        classification_figures(pred.iloc[:4], truth)


def test_normalised_mse_closed_forms():
    rng = np.random.default_rng(3)
    T = 400
    y = rng.normal(size=(T, 3)) * np.array([1.0, 10.0, 0.01]) + np.array([5.0, -2.0, 0.0])
    mu, var = y.mean(0), y.var(0)
    np.testing.assert_allclose(normalised_mse(y, y), 0.0, atol=0)
    np.testing.assert_allclose(normalised_mse(y, np.broadcast_to(mu, y.shape)), 1.0, rtol=1e-12)
    a = np.array([0.0, 0.5, 2.0])
    np.testing.assert_allclose(normalised_mse(y, mu + a * (y - mu)), (1 - a) ** 2, rtol=1e-12)
    c = np.array([0.3, -4.0, 0.02])
    np.testing.assert_allclose(normalised_mse(y, y + c), c ** 2 / var, rtol=1e-12)
    # 1-D input -> one column; a constant truth is not divided by a zero variance.
    assert normalised_mse(y[:, 0], mu[0] + 0 * y[:, 0]).shape == (1,)
    const = np.full(10, 2.0)
    np.testing.assert_allclose(normalised_mse(const, const + 0.5), [0.25], rtol=1e-15)
