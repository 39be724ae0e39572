"""Simulation: the paper's systems and user MJCF files, batched simulation on MuJoCo C or
MuJoCo-Warp, and the random excitation controls datasets are recorded under.

    >>> from gnwarp import sim
    >>> cartpole = sim.make("cartpole")
    >>> m = cartpole.model
    >>> u = sim.random_spline_controls(8, 100, sim.control_range(m), rng=0)     # [8, 100, nu]
    >>> traj = sim.simulate(cartpole, np.tile(m.qpos0, (8, 1)), np.zeros((8, m.nv)), u)
    >>> traj.body.shape                                                         # (8, 101, nbody, 13)

    >>> env = sim.make_env(cartpole, 8, backend="mujoco")                       # persistent worlds
    >>> body = env.reset(np.tile(m.qpos0, (8, 1)))                              # [8, nbody, 13]
    >>> body = env.step(u[:, 0])                                                # one data step

Modules: ``systems`` (registry) over ``families`` (one record per built-in family),
``builders`` (MjSpec of each system) and ``dmc`` (the DeepMind Control Suite's domains,
"dmc-cheetah" ...), ``actuators`` (control ranges, limits, clamping), ``excitation``
(random spline controls), ``backends`` (``simulate``) over ``mujoco_c`` and ``mujoco_warp``,
``common`` (the backends' names and choice, what they share), ``env`` (persistent batched
environments; MuJoCo-Warp datasets run on them too), ``body_state`` (the MuJoCo C body-state reader).
"""
from gnwarp.sim.actuators import Actuators
from gnwarp.sim.common import BACKENDS, Trajectories, resolve_backend
from gnwarp.sim.excitation import control_range, random_spline_controls
from gnwarp.sim.backends import simulate
from gnwarp.sim.env import Env, EnvInputError, make_env
from gnwarp.sim.systems import System, describe, from_mjcf, make, names, param_ranges, param_places, sample_params

__all__ = ["System", "names", "make", "param_ranges", "param_places", "sample_params", "from_mjcf", "describe", "simulate",
           "Trajectories", "BACKENDS", "resolve_backend", "random_spline_controls", "control_range",
           "Env", "EnvInputError", "make_env", "Actuators"]
