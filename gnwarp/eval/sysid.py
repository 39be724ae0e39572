"""Evaluation of system identification (paper Figure 8): rollouts of a ``SysIDModel`` from G_ID
identified on each sequence's first window, of the same instance or of another instance of the
same graph topology (``other_instance_windows``), optionally with G_ID's supervised columns set to
the true parameters (``oracle``); their normalized errors (``sysid_rollout_error``), the
normalized error of any rollouts from a window's end and each sequence's share of it
(``window_errors``), and a model's rows of them (``sysid_error_rows``)."""
from __future__ import annotations

import math

import numpy as np
import torch

from gnwarp.eval.metrics import movable_mask, normalized_errors, sequence_shares
from gnwarp.models.sysid import SysIDModel
from gnwarp.models.sysid_graphs import instance_topologies
from gnwarp.models.sysid_params import ParamStats, with_params

__all__ = ["other_instance_windows", "sysid_rollout_predictions", "sysid_rollout_error", "window_errors",
           "sysid_error_rows"]


def other_instance_windows(dataset, split: str, n: int) -> np.ndarray:
    """For each of the first ``n`` sequences of ``split``, the sequence whose window identifies it
    in the paper's "another instance" test (``sysid_rollout_error(window_from=...)``): the previous
    one among the sequences whose instances share its graph topology (a G_ID has rows per node and
    edge, so it applies only to graphs of its own layout), cyclically. With one topology, as every
    system but the parameterized swimmer has, that is sequence i - 1. A sequence whose topology no
    other shares keeps its own window."""
    topology = instance_topologies(dataset.static)
    groups: dict[tuple, list[int]] = {}
    for i, k in enumerate(np.asarray(dataset[split].instance[:n])):
        groups.setdefault(topology[k], []).append(i)
    src = np.arange(n)
    for rows in groups.values():
        src[rows] = np.roll(rows, 1)
    return src


@torch.no_grad()
def sysid_rollout_predictions(model: SysIDModel, dataset, split: str = "valid", horizon: int = 20,
                              sequences: int | None = None, window_from=None, oracle: ParamStats | None = None
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(predicted [S, H+1, B, 13], true [S, H+1, B, 13], instance [S]) of rollouts from step W of
    each of the first ``sequences`` sequences of ``split``, G_ID identified from its steps
    [0, W) (``window_from`` [S]: the sequences whose windows to use instead, e.g. another
    instance's, for the paper's Figure 8). ``oracle`` (the ``param_stats`` of a model trained
    with ``param_loss``): G_ID's first P global columns are replaced by the instances' true
    standardized parameters, the forward model's predictions when those columns are identified
    perfectly."""
    sp = dataset[split]
    n = len(sp) if sequences is None else min(int(sequences), len(sp))
    W = model.window
    body = torch.as_tensor(np.asarray(sp.body[:n], dtype=np.float32))
    ctrl = torch.as_tensor(np.asarray(sp.ctrl[:n], dtype=np.float32))
    inst = np.asarray(sp.instance[:n])
    H = min(int(horizon), ctrl.shape[1] - W)
    if H < 1:
        raise ValueError(f"the {split} split's sequences are too short for a {W}-step window and a rollout")
    src = np.arange(n) if window_from is None else np.asarray(window_from)
    builder = model.graph_builder(dataset)
    old, model.builder = model.builder, builder
    try:
        g_id = model.identify(body[src, :W], ctrl[src, :W], torch.as_tensor(inst[src]))
        if oracle is not None:
            params = dataset.static.get("params")
            if params is None or np.asarray(params).shape[-1:] != oracle.mean.shape:
                raise ValueError(f"oracle: dataset {dataset.system!r} has no instance parameters of the "
                                 f"{len(oracle.names)} the statistics describe ({', '.join(oracle.names)})")
            g_id = with_params(g_id, *oracle.standardize(np.asarray(params)[inst[src]]))
        pred = model.rollout(body[:, W], ctrl[:, W:W + H], g_id, torch.as_tensor(inst)).float().cpu().numpy()
    finally:
        model.builder = old
    return pred, body[:, W:W + H + 1].numpy(), inst


def sysid_rollout_error(model: SysIDModel, dataset, split: str = "valid", horizon: int = 20,
                        sequences: int | None = None, window_from=None, oracle: ParamStats | None = None) -> float:
    """Mean normalized rollout error (as ``gnwarp.eval.rollout_error``) of the rollouts of
    ``sysid_rollout_predictions`` (same arguments); Inf where they are not finite."""
    pred, true, inst = sysid_rollout_predictions(model, dataset, split, horizon, sequences, window_from, oracle)
    return window_errors(pred, true, movable_mask(dataset, inst))


def window_errors(pred: np.ndarray, true: np.ndarray, mask: np.ndarray, shares: bool = False):
    """Normalized error (``gnwarp.eval.metrics.normalized_errors``) of rollouts ``pred`` and
    ``true`` [S, H+1, B, 13] whose step 0 is the true state, against the constant baseline that
    repeats it; Inf where the predictions are not finite. ``mask``: ``movable_mask``'s bodies.
    ``shares``: (error, each sequence's share of it [S], ``gnwarp.eval.metrics.sequence_shares``)."""
    const = np.broadcast_to(true[:, :1], true.shape)
    r = normalized_errors(pred[:, 1:], true[:, 1:], const[:, 1:], mask)["mean"]
    r = r if math.isfinite(r) else math.inf
    return (r, sequence_shares(pred[:, 1:], true[:, 1:], const[:, 1:], mask)) if shares else r


def sysid_error_rows(model: SysIDModel, dataset, split: str, horizons, sequences: int | None = None,
                     oracle: ParamStats | None = None) -> list[tuple[str, list[float]]]:
    """A system-identification model's rollout errors on the first ``sequences`` sequences of
    ``split`` (default all), one per horizon in ``horizons``: [(label, errors)] with G_ID
    identified from the same instance's window and from another instance's
    (``other_instance_windows``), and with ``oracle`` (its ``param_stats``) a row with G_ID's
    supervised columns set to the true parameters, where ``dataset`` holds them."""
    n = len(dataset[split]) if sequences is None else min(int(sequences), len(dataset[split]))
    rows = [("same instance", None, None), ("another instance", other_instance_windows(dataset, split, n), None)]
    if oracle is not None and "params" in dataset.static:
        rows.append(("same instance, true parameter columns", None, oracle))
    return [(label, [sysid_rollout_error(model, dataset, split, h, n, window_from=src, oracle=o) for h in horizons])
            for label, src, o in rows]
