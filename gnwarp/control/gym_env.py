"""One episode of a control task as a plain ``gymnasium.Env``: a ``ControlVectorEnv`` of one env
(``gnwarp.control.vector_env``) without autoreset, for libraries that take single environments
(and for Gymnasium's own ``check_env``).

    env = make_control_env("pendulum-balance", dynamics="true", episode_steps=200)
    obs, info = env.reset(seed=0)                                   # obs [D] float32
    obs, reward, terminated, truncated, info = env.step(action)     # action [U]

Observations, actions, rewards, the time limit and the dynamics are the vector env's; after a
truncation, call ``reset()`` (stepping on raises ``VectorEnvError``).
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np

from gnwarp.control.vector_env import ControlVectorEnv, make_vector_env

__all__ = ["ControlEnv", "make_control_env"]


class ControlEnv(gym.Env):
    """A ``gymnasium.Env`` over ``vector``, a ``ControlVectorEnv`` of one env with autoreset
    disabled. ``vector`` stays reachable (``body_states``, ``targets``, ``observe()``)."""

    def __init__(self, vector: ControlVectorEnv):
        if vector.num_envs != 1 or vector.autoreset_mode != gym.vector.AutoresetMode.DISABLED:
            raise ValueError("ControlEnv takes a vector env of one env with autoreset_mode='disabled'")
        if vector.output != "numpy":
            raise ValueError("ControlEnv takes a vector env with output='numpy'")
        self.vector = vector
        self.observation_space = vector.single_observation_space
        self.action_space = vector.single_action_space
        self.metadata = {"render_modes": [], "render_fps": vector.metadata["render_fps"]}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """A new episode -> (obs [D], {}); ``seed`` seeds its generator; ``options``: ``qpos``
        [nq], ``qvel`` [nv], ``targets`` (one episode's) to start from."""
        super().reset(seed=seed)
        opts = {k: np.asarray(v, dtype=np.float64).reshape(1, -1) if k in ("qpos", "qvel") else np.asarray(v)[None]
                for k, v in (options or {}).items()}
        obs, _ = self.vector.reset(seed=seed, options=opts)
        return obs[0], {}

    def step(self, action):
        """One step under ``action`` [U] -> (obs [D], reward, False, truncated, {})."""
        obs, r, term, trunc, _ = self.vector.step(np.asarray(action, dtype=np.float64).reshape(1, -1))
        return obs[0], float(r[0]), bool(term[0]), bool(trunc[0]), {}

    def close(self) -> None:
        self.vector.close()


def make_control_env(task, dynamics="true", **kw) -> ControlEnv:
    """One episode of ``task`` as a ``gymnasium.Env``; ``kw``: ``make_vector_env``'s (``backend``,
    ``episode_steps``, ``system``, ``seed``, ``observation``, ``action_repeat``, ...)."""
    for k in ("num_envs", "autoreset_mode", "output"):
        if k in kw:
            raise ValueError(f"make_control_env sets {k} itself (one env, no autoreset, numpy)")
    return ControlEnv(make_vector_env(task, 1, dynamics=dynamics, autoreset_mode="disabled", **kw))
