"""Each effect's regressor columns against an independent closed form or a second computation."""
import numpy as np
import pinocchio as pin
import pytest

from mmgp.physics import effects as fx
from mmgp.physics.context import build_context, smooth_sign_scale
from mmgp.sim import PANDA_JOINTS, panda_urdf_path, reduced_pinocchio_model


@pytest.fixture(scope="module")
def setup():
    model = reduced_pinocchio_model(panda_urdf_path(), PANDA_JOINTS)
    rng = np.random.default_rng(0)
    T = 40
    q = rng.uniform(-1, 1, (T, 7))
    dq = rng.normal(0, 0.5, (T, 7))
    ddq = rng.normal(0, 1.0, (T, 7))
    ctx = build_context(model, q, dq, ddq, v_s=np.full(7, 0.05))
    return model, q, dq, ddq, ctx


def _apply(effect, ctx, coef):
    keys, A = fx.build_atoms([effect], ctx)
    return A @ np.array([coef[k] for k in keys])


def test_nominal_torque_matches_rnea(setup):
    model, q, dq, ddq, ctx = setup
    data = model.createData()
    ref = np.array([pin.rnea(model, data, q[i], dq[i], ddq[i]) for i in range(len(q))])
    np.testing.assert_allclose(ctx.tau_rbd, ref, atol=1e-10)


@pytest.mark.parametrize("cls,params,coef_of,closed", [
    (fx.CoulombFriction, {"tau_c": 1.3}, lambda p, j: {("sign", j): 1.3},
     lambda p, c, j: 1.3 * np.tanh(c.dq[:, j] / 0.05)),
    (fx.ViscousFriction, {"b": 0.7}, lambda p, j: {("dq", j): 0.7}, lambda p, c, j: 0.7 * c.dq[:, j]),
    (fx.Armature, {"inertia": 0.2}, lambda p, j: {("ddq", j): 0.2}, lambda p, c, j: 0.2 * c.ddq[:, j]),
    (fx.TorqueOffset, {"offset": -0.4}, lambda p, j: {("one", j): -0.4}, lambda p, c, j: np.full(c.T, -0.4)),
    (fx.JointSpring, {"k": 5.0, "q0": 0.3}, lambda p, j: {("q", j): 5.0, ("one", j): -1.5},
     lambda p, c, j: 5.0 * (c.q[:, j] - 0.3)),
    (fx.LoadDependentFriction, {"tau_c": 0.2, "beta": 0.1}, lambda p, j: {("sign", j): 0.2, ("load", j): 0.1},
     lambda p, c, j: (0.2 + 0.1 * np.abs(c.tau_rbd[:, j])) * np.sign(c.dq[:, j]) * np.tanh(np.abs(c.dq[:, j]) / 0.05)),
])
def test_joint_effect_columns(setup, cls, params, coef_of, closed):
    *_, ctx = setup
    j = 3
    e = cls(j)
    got = _apply(e, ctx, coef_of(params, j))
    want = np.zeros((ctx.T, 7))
    want[:, j] = closed(params, ctx, j)
    np.testing.assert_allclose(got, want, atol=1e-12)
    np.testing.assert_allclose(e.torque(params, ctx), want, atol=1e-12)
    # coefficients -> physical parameters round trip
    p, _ = e.params(coef_of(params, j), {})
    for k, v in params.items():
        assert p[k] == pytest.approx(v)


def test_encoder_offset_linearises_rnea(setup):
    """Column times offset = tau_rbd(q_log) - tau_rbd(q_log - offset) to first order."""
    model, q, dq, ddq, ctx = setup
    data = model.createData()
    j, off = 1, 1e-5
    qt = q.copy()
    qt[:, j] -= off
    ref = np.array([pin.rnea(model, data, qt[i], dq[i], ddq[i]) for i in range(len(q))]) - ctx.tau_rbd
    got = _apply(fx.EncoderOffset(j), ctx, {("enc", j): off})
    np.testing.assert_allclose(got, ref, atol=1e-8, rtol=1e-4)


def _heavier_rnea(model, link, m, c, q, dq, ddq, ctx):
    """(T, n) what a point mass ``m`` at ``c`` on ``link`` adds: Pinocchio's RNEA of the model whose
    link inertia includes it, less the nominal torque."""
    heavy = model.copy()
    heavy.inertias[link + 1] = heavy.inertias[link + 1] + pin.Inertia(m, c, np.zeros((3, 3)))
    data = heavy.createData()
    return np.array([pin.rnea(heavy, data, q[i], dq[i], ddq[i]) for i in range(len(q))]) - ctx.tau_rbd


def test_payload_columns_match_heavier_link(setup):
    """A point mass on link 6 (0-based) = the RNEA of a model whose link inertia includes it."""
    model, q, dq, ddq, ctx = setup
    link, m, c = 6, 0.9, np.array([0.02, -0.01, 0.12])
    ctx.payload_com[link] = c
    got = fx.Payload(link).torque({"mass": m, "com": c}, ctx)
    got2 = _apply(fx.Payload(link), ctx, {("pl", link, 0): m, ("pl", link, 1): m * c[0],
                                          ("pl", link, 2): m * c[1], ("pl", link, 3): m * c[2]})
    ref = _heavier_rnea(model, link, m, c, q, dq, ddq, ctx)
    np.testing.assert_allclose(got, ref, atol=1e-9)
    np.testing.assert_allclose(got2, ref, atol=1e-9)
    p, _ = fx.Payload(link).params({("pl", link, 0): m, ("pl", link, 1): m * c[0], ("pl", link, 2): m * c[1],
                                     ("pl", link, 3): m * c[2]}, {})
    assert p["mass"] == pytest.approx(m) and np.allclose(p["com"], c)


def test_a_held_payload_direction_has_no_first_moment(setup):
    """With the centre of mass held on a line through the link origin (``payload_held``), the
    columns are those of the point mass on that line (RNEA of the heavier model), whatever the
    linearisation guess, and a first moment along the held direction moves no joint."""
    model, q, dq, ddq, ctx = setup
    link, m = 6, 0.9
    v = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
    guess = np.array([0.02, -0.01, 0.12])
    held = ctx.with_payload_com(link, guess).with_payload_held(link, v[None, :])
    c = guess - (guess @ v) * v
    got = _apply(fx.Payload(link), held, {("pl", link, 0): m, ("pl", link, 1): m * c[0],
                                           ("pl", link, 2): m * c[1], ("pl", link, 3): m * c[2]})
    ref = _heavier_rnea(model, link, m, c, q, dq, ddq, ctx)
    np.testing.assert_allclose(got, ref, atol=1e-9)
    along = _apply(fx.Payload(link), held, {("pl", link, 0): 0.0, ("pl", link, 1): v[0], ("pl", link, 2): v[1],
                                             ("pl", link, 3): v[2]})
    np.testing.assert_allclose(along, 0.0, atol=1e-12)


def test_smooth_sign_scale_tracks_noise():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 10, 5000)
    clean = np.sin(t)[:, None]
    for sigma in (0.001, 0.01):
        vs = smooth_sign_scale(clean + sigma * rng.standard_normal(clean.shape), k=3.0, speed_frac=0.0, floor_frac=0.0)
        assert vs[0] == pytest.approx(3 * sigma, rel=0.15)


def test_smooth_sign_scale_on_a_clean_log_is_a_fraction_of_the_speed():
    # dq = sin(t) over whole periods: |sin| of a uniform phase has P(|sin| <= x) = (2/pi) arcsin(x),
    # so its 95th percentile is sin(0.95 pi / 2); noise-free, the speed term decides.
    t = np.linspace(0, 2 * np.pi * 20, 200001)
    vs = smooth_sign_scale(np.sin(t)[:, None])
    assert vs[0] == pytest.approx(0.05 * np.sin(0.95 * np.pi / 2), rel=1e-3)
