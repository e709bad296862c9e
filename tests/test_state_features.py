"""The one recipe from states to GP inputs and targets (issue 32): StateFeatures against closed
forms and Pinocchio's RNEA called directly."""
import numpy as np
import pinocchio as pin

import mmgp
from mmgp.labelling.features import StateFeatures


def _states(T=40, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-1, 1, (T, 1)), rng.normal(scale=0.2, size=(T, 1)), rng.normal(size=(T, 1)),
            rng.normal(size=(T, 1)))


def test_inputs_and_targets_against_closed_forms_and_pinocchio():
    q, dq, ddq, tau = _states()
    v_s = np.array([0.05])
    urdf = mmgp.demo_urdf()
    robot = mmgp.load_robot(urdf=urdf)
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    rnea = np.array([pin.rnea(model, data, q[t], dq[t], ddq[t]) for t in range(len(q))])
    faded = np.tanh(dq / v_s) * (1.0 - np.exp(-0.5 * (dq / v_s) ** 2))       # sign x (1 - rest weight)

    f = StateFeatures("residual", robot, v_s)(q, dq, ddq, tau, starts=(0, 20))
    np.testing.assert_allclose(f.X, np.hstack([q, dq, ddq, faded]), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(f.Y, tau - rnea, rtol=1e-10, atol=1e-12)
    assert f.starts == [0, 20] and f.has_sign and f.basis is None

    plain = StateFeatures("none", friction_scale=v_s, sign_fades=False)(q, dq, ddq, tau)     # the diagnosis's learner
    np.testing.assert_array_equal(plain.X[:, 3], np.tanh(dq[:, 0] / v_s[0]))
    assert plain.tau_rbd is None and np.array_equal(plain.Y, tau)

    feature = StateFeatures("feature", robot)(q, dq, ddq, tau)                   # compare's peer: no friction input
    np.testing.assert_allclose(feature.X, np.hstack([q, dq, ddq, rnea]), rtol=1e-10, atol=1e-12)
    assert np.array_equal(feature.Y, tau) and not feature.has_sign

    branch = StateFeatures("residual", robot, v_s)(q, dq, ddq, tau, friction_sign=-1.0)
    assert np.all(branch.X[:, 3] == -1.0)


def test_features_of_logs_join_them_in_time_order():
    from mmgp.data.logs import log_from_arrays

    q, dq, ddq, tau = _states(60, seed=1)
    t = np.arange(60) * 0.01
    logs = [log_from_arrays(t[:25], q[:25], tau[:25], dq=dq[:25], ddq=ddq[:25]),
            log_from_arrays(t[25:] - t[25], q[25:], tau[25:], dq=dq[25:], ddq=ddq[25:])]
    f = StateFeatures("none", friction_scale=np.array([0.05]))
    whole, joined = f(q, dq, ddq, tau), f.of_logs(logs)
    np.testing.assert_array_equal(joined.X, whole.X)
    assert joined.starts == [0, 25] and np.array_equal(joined.t, np.r_[t[:25], t[25:] - t[25]])
    assert joined.muted.shape == (1,) and not joined.muted.any()
