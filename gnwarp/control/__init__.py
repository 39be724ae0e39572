"""Control with learned models (supplementary F): tasks and their rewards on graph states
(``tasks``: the paper's; ``dmc``: the DeepMind Control Suite's, "dmc-<domain>-<task>"; ``task_base``:
the ``Task`` record), gradient MPC through a learned model (``gradient``), sampling MPC
(``sampling``), the hybrid of both (``hybrid``), what planners maximize (``returns``: discount,
terminal value, gradient conditioning), a learned terminal value (``value``), the iLQG baseline
(``ilqg``), the ``Planner`` protocol they all implement with the registry of planner names
(``planner``), closed-loop episodes (``episodes``) and their planning times, the first step apart
from the steady state (``timing``), Gymnasium vector environments on the true or learned dynamics
(``vector_env``) and the data loop (``data_loop``); the batched true environment they run on is
``gnwarp.sim.env``.

    >>> from gnwarp import control
    >>> task = control.get_task("pendulum-balance")
    >>> planner = control.GradientMPC(model, task, systems.make("pendulum"), n=64)
    >>> out = control.run_episodes(planner, env, task, steps=100, x0=env.reset(...))
"""
from gnwarp.control.episodes import identify_on_env, run_episodes
from gnwarp.control.gradient import GradientMPC, GradientMPCConfig
from gnwarp.control.returns import PlanningError
from gnwarp.control.hybrid import HybridConfig, HybridPlanner
from gnwarp.control.planner import PLANNERS, Planner, get_planner, planner_name
from gnwarp.control.tasks import TASKS, Task, TaskError, episode_starts, get_task, sample_targets, task_names
from gnwarp.control.timing import control_timestep, plan_timing
from gnwarp.control.value import TerminalValue, fit_terminal_value
from gnwarp.control.vector_env import ControlVectorEnv, make_vector_env

__all__ = ["Task", "TASKS", "TaskError", "get_task", "task_names", "sample_targets", "episode_starts", "GradientMPC",
           "GradientMPCConfig", "PlanningError", "Planner", "PLANNERS", "get_planner", "planner_name", "run_episodes",
           "identify_on_env", "plan_timing", "control_timestep", "HybridPlanner", "HybridConfig", "TerminalValue",
           "fit_terminal_value", "make_vector_env", "ControlVectorEnv"]
