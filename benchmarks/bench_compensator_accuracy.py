"""What the gradient constraint costs: curl-free potential GP vs unconstrained per-joint GPs.

Truth (a stand-in for a trained model's nominal torque at dq = ddq = 0): Panda gravity with a
1.5 kg payload on the hand (Pinocchio), a joint spring on joint 2 (k = 8 N*m/rad, q0 = 0.3 rad)
and a 0.6 N*m torque offset on joint 4. All three are conservative, as any true position-only
torque of a robot is. Both learners get the same N random configurations (within the joint
limits, or within +-``--half-width`` rad of a home pose) and are scored on 2,000 held-out ones:

  * ours: ``compensator_from_model`` (curl-free RBF potential, tau = grad V exactly),
  * peer: seven independent ARD-RBF GPs (``IndependentJointGPs``), the usual unconstrained choice,
  * reference: the nominal rigid-body model alone (no payload, spring or offset).

Printed: RMSE per joint (N*m), overall normalised MSE (sum of squared errors over the sum of
squared deviations of the truth), fit time, and ``check_passivity`` for both learners.

    python benchmarks/bench_compensator_accuracy.py [--n 1000] [--half-width 0.6]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from mmgp.compensator import check_passivity, compensator_from_model
from mmgp.gp.gradient_field import RBFGP

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
HOME = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])


class IndependentJointGPs:
    """Unconstrained peer: one RBF GP per joint torque (not a gradient field in general).

    ``storage`` is the naive candidate a per-joint design would use: each joint's torque
    integrated along its own axis (an erf in that coordinate times the Gaussian in the others).
    Its gradient matches the torque only on the diagonal, and the loop work of ``torque`` is
    generally non-zero: check_passivity must reject it.
    """

    def __init__(self, max_hyper_points=500, max_iter=100, seed=0):
        self.max_hyper_points, self.max_iter, self.seed = max_hyper_points, max_iter, seed

    def fit(self, Q, Y):
        self.gps_ = [RBFGP(self.max_hyper_points, self.max_iter, seed=self.seed).fit(Q, Y[:, i])
                     for i in range(Y.shape[1])]
        self.n_joints = Q.shape[1]
        self.bounds = np.stack([Q.min(0), Q.max(0)])
        return self

    def torque(self, q):
        q2 = np.asarray(q, dtype=np.float64).reshape(-1, self.n_joints)
        out = np.stack([g.predict(q2) for g in self.gps_], axis=1)
        return out[0] if np.ndim(q) == 1 else out

    def storage(self, q):
        from scipy.special import erf

        q2 = np.asarray(q, dtype=np.float64).reshape(-1, self.n_joints)
        S = np.zeros(q2.shape[0])
        for i, g in enumerate(self.gps_):
            U = (q2[:, None, :] - g.support_[None]) / g.lengthscales_
            others = np.exp(-0.5 * (np.sum(U * U, axis=2) - U[:, :, i] ** 2))
            amp = g.signal_var_ * g.lengthscales_[i] * np.sqrt(np.pi / 2) * g.alpha_[:, 0]
            S += (erf(U[:, :, i] / np.sqrt(2.0)) * others) @ amp
        return float(S[0]) if np.ndim(q) == 1 else S


class Truth:
    def __init__(self, robot, lo, hi, n, seed):
        self.robot = robot.add_payload("panda_hand", 1.5, [0.0, 0.0, 0.08])
        self.lo, self.hi = lo, hi
        rng = np.random.default_rng(seed)
        self.support_q_ = lo + (hi - lo) * rng.random((n, robot.n_joints))
        self.joint_names_ = robot.joint_names

    def nominal_torque(self, q):
        q = np.atleast_2d(q)
        tau = self.robot.gravity(q)
        tau[:, 1] += 8.0 * (q[:, 1] - 0.3)
        tau[:, 3] += 0.6
        return tau


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1000, help="training configurations (= support points)")
    ap.add_argument("--half-width", type=float, default=0.6,
                    help="rad around the home pose; 0 = the full joint limits")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from mmgp.physics.robot import RobotModel

    robot = RobotModel.from_name("panda", PANDA_JOINTS)
    lim_lo, lim_hi = robot.pin_model.lowerPositionLimit.copy(), robot.pin_model.upperPositionLimit.copy()
    if args.half_width > 0:
        lo, hi = np.maximum(HOME - args.half_width, lim_lo), np.minimum(HOME + args.half_width, lim_hi)
        region = f"home pose +- {args.half_width} rad"
    else:
        lo, hi, region = lim_lo, lim_hi, "full joint limits"
    truth = Truth(robot, lo, hi, args.n, args.seed)
    Qte = lo + (hi - lo) * np.random.default_rng(args.seed + 100).random((2000, 7))
    ref = truth.nominal_torque(Qte)

    t0 = time.perf_counter()
    comp = compensator_from_model(truth, max_support=args.n, seed=args.seed)
    t_ours = time.perf_counter() - t0
    Ytr = truth.nominal_torque(truth.support_q_)
    t0 = time.perf_counter()
    ind = IndependentJointGPs(max_hyper_points=500, max_iter=75, seed=args.seed).fit(truth.support_q_, Ytr)
    t_ind = time.perf_counter() - t0

    preds = {"ours: curl-free potential GP": comp.torque(Qte),
             "peer: independent per-joint GPs": ind.torque(Qte),
             "rigid-body model alone": robot.gravity(Qte)}
    denom = np.sum((ref - ref.mean(0)) ** 2)
    print(f"Panda, {region}, N = {args.n} training configurations, 2000 held out")
    print(f"truth torque RMS per joint (N*m): {np.array2string(np.sqrt(np.mean(ref ** 2, 0)), precision=3)}")
    print(f"{'predictor':34s} {'nMSE':>9s}  RMSE per joint (N*m)")
    for name, p in preds.items():
        e = p - ref
        print(f"{name:34s} {np.sum(e ** 2) / denom:9.2e}  "
              f"{np.array2string(np.sqrt(np.mean(e ** 2, 0)), precision=4, max_line_width=200)}")
    print(f"fit time: ours {t_ours:.1f} s (incl. bound/sampled-min), peer {t_ind:.1f} s")
    print(f"ours: lengthscales {np.array2string(np.asarray(comp.info['lengthscales']), precision=3)}, "
          f"rigorous |V| bound {comp.potential_bound:.1f} J (triangle bound "
          f"{comp.bound_info['triangle_bound']:.3g} J), sampled storage min over the box {comp.storage_sampled_min:.1f} J")
    for name, obj in (("ours", comp), ("peer", ind)):
        r = check_passivity(obj, n_configs=100, n_loops=30, bounds=np.stack([lo, hi]))
        print(f"check_passivity {name}: passed={r['passed']} loop work/(torque*length)={r['loop_max_rel_work']:.2e} "
              f"max |loop work|={r['loop_max_abs_work']:.2e} J grad err={r['grad_max_rel_err']:.2e}")


if __name__ == "__main__":
    main()
