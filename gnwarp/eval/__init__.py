"""Evaluation: the paper's normalized one-step and rollout errors, their tables and plots, and
animations of true vs predicted motion.

    >>> from gnwarp import eval as ev
    >>> results = {"GN": ev.evaluate(model, dataset, "test")}
    >>> print(ev.markdown_table(results, dataset.system))

Modules: ``metrics`` (errors), ``report`` (tables and plots), ``animation`` (GIFs), ``render``
(MuJoCo's offscreen renderer in a child process), ``sysid`` (rollouts from identified parameters).
"""
from gnwarp.eval.animation import animate, animate_system
from gnwarp.eval.metrics import (evaluate, movable_mask, normalized_errors, one_step_predictions, rollout_error,
                                 rollout_predictions, sequence_shares, squared_errors)
from gnwarp.eval.render import RenderUnavailable, render_rollouts
from gnwarp.eval.sysid import (other_instance_windows, sysid_error_rows, sysid_rollout_error, sysid_rollout_predictions,
                               window_errors)
from gnwarp.eval.report import markdown_table, plot_errors, plot_state_traces, plot_training, write_report
from gnwarp.state import GROUPS

__all__ = ["evaluate", "rollout_error", "rollout_predictions", "one_step_predictions", "normalized_errors",
           "sequence_shares", "squared_errors", "movable_mask", "GROUPS", "markdown_table", "plot_errors",
           "plot_state_traces", "plot_training", "animate", "animate_system", "render_rollouts", "RenderUnavailable",
           "other_instance_windows", "sysid_rollout_predictions", "sysid_rollout_error", "sysid_error_rows",
           "window_errors", "write_report"]
