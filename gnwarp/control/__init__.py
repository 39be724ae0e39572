"""Control with learned models (supplementary F): tasks and their rewards on graph states
(``tasks``: the paper's; ``dmc``: the DeepMind Control Suite's, "dmc-<domain>-<task>"; ``task_base``:
the ``Task`` record), gradient MPC through a learned model (``gradient``), sampling MPC (``sampling``), the
iLQG baseline (``ilqg``), the ``Planner`` protocol they all implement with the registry of planner
names (``planner``), closed-loop episodes (``episodes``) and their planning times, the first step
apart from the steady state (``timing``); the batched true environment they run on is
``gnwarp.sim.env``.

    >>> from gnwarp import control
    >>> task = control.get_task("pendulum-balance")
    >>> planner = control.GradientMPC(model, task, systems.make("pendulum"), n=64)
    >>> out = control.run_episodes(planner, env, task, steps=100, x0=env.reset(...))
"""
from gnwarp.control.episodes import identify_on_env, run_episodes
from gnwarp.control.gradient import GradientMPC, GradientMPCConfig, PlanningError
from gnwarp.control.planner import PLANNERS, Planner, get_planner, planner_name
from gnwarp.control.tasks import TASKS, Task, TaskError, get_task, sample_targets, task_names
from gnwarp.control.timing import control_timestep, plan_timing

__all__ = ["Task", "TASKS", "TaskError", "get_task", "task_names", "sample_targets", "GradientMPC",
           "GradientMPCConfig", "PlanningError", "Planner", "PLANNERS", "get_planner", "planner_name", "run_episodes",
           "identify_on_env", "plan_timing", "control_timestep"]
