"""Errors of forward models the way the paper measures them (section 4, Figs. 4-5).

Errors are squared differences of the body states, computed separately for position,
orientation (sign-invariant: min over q and -q), linear and angular velocity (each summed over
its features, averaged over movable bodies, steps and sequences), each divided by the error of the
constant-prediction baseline (the input state predicted unchanged), then averaged over the four
groups. Groups the constant baseline predicts exactly (e.g. a Pendulum body's position: its frame
sits on the hinge) have no such ratio and are left out of the average.

- one-step: predictions from the true state at every step of the test sequences;
- rollout at H steps: rollouts from the first state of each test sequence under its true
  controls, errors averaged over the H predicted steps (the baseline repeats the first state).

``evaluate`` gives the numbers; ``gnwarp.eval.report`` turns them into tables and plots.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from gnwarp.state import GROUPS

__all__ = ["movable_mask", "body_mask", "squared_errors", "rollout_predictions", "one_step_predictions",
           "normalized_errors", "sequence_shares", "first_nonfinite_steps", "rollout_error", "evaluate"]


def movable_mask(dataset, instance: np.ndarray) -> np.ndarray:
    """[S, B] bool: bodies that exist (not padding) and are not the world body."""
    n_node = np.asarray(dataset.static["n_node"])[np.asarray(instance)]
    B = np.asarray(dataset.static["nodes"]).shape[1]
    b = np.arange(B)[None]
    return (b >= 1) & (b < n_node[:, None])


def body_mask(dataset, instance: np.ndarray) -> np.ndarray:
    """[S, B] bool: bodies that exist (not padding), the world body included."""
    n_node = np.asarray(dataset.static["n_node"])[np.asarray(instance)]
    B = np.asarray(dataset.static["nodes"]).shape[1]
    return np.arange(B)[None] < n_node[:, None]


def first_nonfinite_steps(pred: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[S] int: for predicted states [S, H+1, B, 13] (bodies ``mask`` [S, B]), the first step at
    which a body's state is NaN or Inf; -1 where a sequence stays finite."""
    bad = (~np.isfinite(pred).all(-1) & mask[:, None]).any(-1)   # [S, H+1]
    return np.where(bad.any(1), bad.argmax(1), -1)


def squared_errors(pred: np.ndarray, true: np.ndarray) -> dict[str, np.ndarray]:
    """{group: [...] squared error summed over the group's features} for states [..., 13]."""
    out = {}
    for g, sl in GROUPS.items():
        if g == "quat":
            a = ((pred[..., sl] - true[..., sl]) ** 2).sum(-1)
            b = ((pred[..., sl] + true[..., sl]) ** 2).sum(-1)
            out[g] = np.minimum(a, b)
        else:
            out[g] = ((pred[..., sl] - true[..., sl]) ** 2).sum(-1)
    return out


def _split_arrays(dataset, split: str, sequences: int | None):
    sp = dataset[split]
    n = len(sp) if sequences is None else min(int(sequences), len(sp))
    if n == 0:
        raise ValueError(f"the {split} split of {dataset.system!r} is empty")
    body = np.asarray(sp.body[:n], dtype=np.float32)
    ctrl = np.asarray(sp.ctrl[:n], dtype=np.float32)
    inst = np.asarray(sp.instance[:n])
    return body, ctrl, inst


@torch.no_grad()
def rollout_predictions(model, dataset, split: str = "test", horizon: int = 100, sequences: int | None = None,
                        batch_size: int = 1024, engine=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(predicted [S, H+1, B, 13], true [S, H+1, B, 13], instance [S]) of H-step rollouts from the
    first state of the first ``sequences`` sequences of ``split`` under their true controls.
    ``engine``: a ``RolloutEngine`` of exactly these S sequences and H steps (one batch, replayed
    from a CUDA graph on CUDA: ``ForwardModel.rollout_engine``)."""
    body, ctrl, inst = _split_arrays(dataset, split, sequences)
    H = min(int(horizon), ctrl.shape[1])
    if engine is not None:
        pred = engine.rollout(torch.as_tensor(body[:, 0]), torch.as_tensor(ctrl[:, :H]))
        return pred.float().cpu().numpy(), body[:, :H + 1], inst
    builder = model.graph_builder(dataset)
    preds = []
    for a in range(0, body.shape[0], batch_size):
        b = slice(a, a + batch_size)
        r = model.rollout(torch.as_tensor(body[b, 0]), torch.as_tensor(ctrl[b, :H]), torch.as_tensor(inst[b]),
                          builder=builder)
        preds.append(r.float().cpu().numpy())
    return np.concatenate(preds), body[:, :H + 1], inst


@torch.no_grad()
def one_step_predictions(model, dataset, split: str = "test", sequences: int | None = None,
                         batch_size: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(predicted [S, T, B, 13] of x_{t+1} from the true x_t, true [S, T+1, B, 13], instance [S])."""
    body, ctrl, inst = _split_arrays(dataset, split, sequences)
    S, T = ctrl.shape[:2]
    x = body[:, :T].reshape(S * T, *body.shape[2:])
    u = ctrl.reshape(S * T, 1, -1)
    i = np.repeat(inst, T)
    builder = model.graph_builder(dataset)
    preds = []
    for a in range(0, S * T, batch_size):
        b = slice(a, a + batch_size)
        r = model.rollout(torch.as_tensor(x[b]), torch.as_tensor(u[b]), torch.as_tensor(i[b]), builder=builder)
        preds.append(r[:, 1].float().cpu().numpy())
    return np.concatenate(preds).reshape(S, T, *body.shape[2:]), body, inst


def normalized_errors(pred: np.ndarray, true: np.ndarray, const: np.ndarray, mask: np.ndarray) -> dict:
    """Errors of ``pred`` and of the constant prediction ``const`` against ``true`` (all [S, H, B, 13],
    ``mask`` [S, B]): {"pos"/"quat"/"linvel"/"angvel": ratio, "mean": mean ratio, "model": {group:
    mean squared error}, "constant": {...}}. A group the constant baseline predicts exactly has no
    ratio (NaN, left out of the mean); where the model's predictions are not finite the ratio and
    the mean are Inf (never NaN: a diverged model is not a group without a ratio)."""
    w = np.broadcast_to(mask[:, None], pred.shape[:3]).astype(np.float64)
    em, ec = squared_errors(pred, true), squared_errors(const, true)
    out = {"model": {}, "constant": {}}
    for g in GROUPS:
        out["model"][g] = float((em[g] * w).sum() / max(w.sum(), 1))
        out["constant"][g] = float((ec[g] * w).sum() / max(w.sum(), 1))
    scale = max(out["constant"].values())
    ratios = []
    for g in GROUPS:
        c = out["constant"][g]
        # a group the constant baseline gets right up to float32 rounding has no meaningful ratio
        m = out["model"][g]
        if not math.isfinite(m):
            r = math.inf       # predictions left the finite range
        else:
            r = m / c if c > 1e-8 * scale and c > 0 else math.nan
        out[g] = r
        if not math.isnan(r):
            ratios.append(r)
    out["mean"] = float(np.mean(ratios)) if ratios else math.nan
    return out


def sequence_shares(pred: np.ndarray, true: np.ndarray, const: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each sequence's share [S] of ``normalized_errors(pred, true, const, mask)["mean"]``: its
    squared error per group over the pooled constant-baseline error, averaged over the groups
    that have a ratio. The shares sum to the mean error, so they show whether a few sequences
    carry it (a mean of squared rollout errors is dominated by the rollouts that drift furthest).
    A sequence whose predictions are not finite (in any group) has an Inf share, and the error
    is Inf too."""
    w = np.broadcast_to(mask[:, None], pred.shape[:3]).astype(np.float64)
    em, ec = squared_errors(pred, true), squared_errors(const, true)
    total = max(w.sum(), 1)
    const_mse = {g: float((ec[g] * w).sum() / total) for g in GROUPS}
    scale = max(const_mse.values())
    shares = [(em[g] * w).sum(axis=(1, 2)) / total / c for g, c in const_mse.items() if c > 1e-8 * scale and c > 0]
    if not shares:
        return np.full(pred.shape[0], np.nan)
    out = np.mean(shares, axis=0)
    # as ``normalized_errors``: predictions that left the finite range in any group are Inf
    finite = np.all([np.isfinite((em[g] * w).sum(axis=(1, 2))) for g in GROUPS], axis=0)
    out[~finite] = np.inf
    return out


def rollout_error(model, dataset, split: str = "valid", horizon: int = 20, sequences: int | None = None,
                  engine=None) -> float:
    """Mean normalized rollout error over ``horizon`` steps (the validation metric of D.8);
    ``engine``: see ``rollout_predictions``."""
    pred, true, inst = rollout_predictions(model, dataset, split, horizon, sequences, engine=engine)
    const = np.broadcast_to(true[:, :1], true.shape)
    r = normalized_errors(pred[:, 1:], true[:, 1:], const[:, 1:], movable_mask(dataset, inst))["mean"]
    return r if math.isfinite(r) else math.inf


def evaluate(model, dataset, split: str = "test", sequences: int | None = None,
             horizons: tuple[int, ...] = (20, 100), keep_predictions: bool = False) -> dict:
    """{"one_step": errors, "rollout_20": errors, "rollout_100": errors, ...} (see
    ``normalized_errors``) on the first ``sequences`` sequences of ``split``. Horizons longer than
    the sequences are cut to their length (the key keeps the asked horizon and "steps" says how
    many were used). ``keep_predictions``: also return the longest rollout under "predictions".

    Predictions that leave the finite range are reported, not hidden: their errors are Inf,
    each horizon's "first_nonfinite_step" is the first rollout step (1..H) at which any sequence's
    state was NaN or Inf (None: finite throughout), "nonfinite_sequences" how many sequences left
    the range, and the one-step errors' "nonfinite_steps" how many one-step predictions did."""
    was_training = model.training
    model.eval()
    try:
        out = {}
        pred, true, inst = one_step_predictions(model, dataset, split, sequences)
        mask = movable_mask(dataset, inst)
        bodies = body_mask(dataset, inst)
        out["one_step"] = normalized_errors(pred, true[:, 1:], true[:, :-1], mask)
        out["one_step"]["steps"] = 1
        out["one_step"]["nonfinite_steps"] = int((~np.isfinite(pred).all(-1) & bodies[:, None]).any(-1).sum())
        H = max(horizons) if horizons else 0
        if H:
            pred, true, inst = rollout_predictions(model, dataset, split, H, sequences)
            const = np.broadcast_to(true[:, :1], true.shape)
            first = first_nonfinite_steps(pred, bodies)
            for h in horizons:
                k = min(h, pred.shape[1] - 1)
                r = normalized_errors(pred[:, 1:k + 1], true[:, 1:k + 1], const[:, 1:k + 1], mask)
                gone = (first >= 0) & (first <= k)
                r["steps"] = k
                r["first_nonfinite_step"] = int(first[gone].min()) if gone.any() else None
                r["nonfinite_sequences"] = int(gone.sum())
                out[f"rollout_{h}"] = r
            # stability: the rollout stayed finite, else the first step where it did not
            out["finite"] = bool((first < 0).all())
            out["first_nonfinite_step"] = int(first[first >= 0].min()) if (first >= 0).any() else None
            out["nonfinite_sequences"] = int((first >= 0).sum())
            if keep_predictions:
                out["predictions"] = {"pred": pred, "true": true, "instance": inst}
        out["sequences"] = int(mask.shape[0])
        return out
    finally:
        model.train(was_training)
