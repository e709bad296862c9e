"""MuJoCo recordings: the simulated "real robot" used by the demo data, tests and benchmarks.

An optional side package (``pip install mmgp[sim]``): the core of mmgp never imports it.
MuJoCo is the independent physics engine here: recordings never come from Pinocchio's equations,
so a Pinocchio-based learner can be checked against them. Modules:

* :mod:`.mjcf`: MJCF models of URDF robots through Pinocchio's parse, payload bodies.
* :mod:`.recording`: the 1 kHz tracking loop :func:`simulate`, :class:`Push`, :class:`Recording`,
  the contract label rule.
* :mod:`.excitation`: reference trajectories and push schedules.
* :mod:`.scenarios`: the stock recordings :func:`actuator_replica` and :func:`panda_modes`.
* :mod:`.concealed`: recordings with concealed effects and their truth, for the diagnosis.
* :mod:`.inverse`: MuJoCo inverse dynamics of a logged trajectory (dry friction as a law), e.g. of
  the corrected model ``mmgp diagnose`` writes.
"""
try:
    import mujoco  # noqa: F401
except ImportError as exc:  # the one message a user without the extra sees
    raise ImportError("mmgp.sim needs MuJoCo, which is optional: install mmgp[sim] "
                      "(pip install 'mmgp[sim]')") from exc

from .excitation import fourier_reference, push_schedule, sines_reference, sinusoid_reference
from .inverse import FRICTION_VELOCITY, explained_share, friction_velocity, inverse_dynamics
from .mjcf import (NOSLIP_ITERATIONS, body_name, build_mjcf, load_model, panda_urdf_path, reduced_pinocchio_model,
                   robot_urdf_path, set_payload)
from .recording import LABEL_RULE, Push, Recording, contract_disturbed, simulate
from .scenarios import (PANDA, PANDA_JOINTS, REPLICA, actuator_replica, panda_modes, random_link_pushes,
                        replica_mjcf)

__all__ = [
    "FRICTION_VELOCITY", "LABEL_RULE", "NOSLIP_ITERATIONS", "PANDA", "PANDA_JOINTS", "REPLICA", "Push", "Recording",
    "actuator_replica", "body_name", "build_mjcf", "contract_disturbed", "explained_share", "fourier_reference", "friction_velocity",
    "inverse_dynamics", "load_model",
    "panda_modes", "panda_urdf_path", "push_schedule", "random_link_pushes", "reduced_pinocchio_model",
    "replica_mjcf", "robot_urdf_path", "set_payload", "simulate", "sines_reference", "sinusoid_reference",
]
