"""The instance parameters a system-identification model's G_ID is taught (``SysIDTrainConfig.param_loss``):
their statistics over a dataset's train split (``ParamStats``, ``param_stats``), read back from
G_ID (``estimate_params``) or written into it (``with_params``)."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from gnwarp.graphs import GraphsTuple

__all__ = ["ParamStats", "param_stats", "estimate_params", "with_params"]


class ParamStats(NamedTuple):
    """A dataset's parameters as ``param_loss`` standardizes them: ``names`` [P], ``mean`` [P],
    ``std`` [P] over the train split's instances; ``used`` [P]: parameters that vary there."""
    names: list
    mean: np.ndarray
    std: np.ndarray
    used: np.ndarray

    def standardize(self, params) -> tuple[np.ndarray, np.ndarray]:
        """(z [..., P], ok [..., P]): ``params`` standardized, 0 where ``ok`` is False (a NaN, or a
        parameter that did not vary in training)."""
        raw = np.asarray(params, dtype=np.float64)
        ok = np.isfinite(raw) & self.used
        return np.where(ok, (np.nan_to_num(raw) - self.mean) / self.std, 0.0), ok

    def to_dict(self) -> dict:
        """As a checkpoint's config.json keeps it (``from_dict`` reads it back)."""
        return {"names": list(self.names), "mean": self.mean.tolist(), "std": self.std.tolist(),
                "used": self.used.tolist()}

    @classmethod
    def from_dict(cls, d) -> "ParamStats":
        """The statistics a checkpoint's config.json keeps (``param_stats`` per system), checked:
        P names, P finite means and standard deviations (positive where used), P flags."""
        if not isinstance(d, dict) or set(d) != {"names", "mean", "std", "used"}:
            raise ValueError(f"parameter statistics need names, mean, std and used, got {d!r:.80}")
        names = d["names"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError("parameter statistics: names must be a list of strings")
        try:
            mean, std = (np.asarray(d[k], dtype=np.float64) for k in ("mean", "std"))
            used = np.asarray(d["used"])
        except (TypeError, ValueError):
            raise ValueError("parameter statistics: mean and std must be lists of numbers") from None
        P = len(names)
        if any(a.shape != (P,) for a in (mean, std, used)) or used.dtype != np.bool_:
            raise ValueError(f"parameter statistics: mean, std and used must each hold {P} values (used: booleans)")
        if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std[used] > 0).all()):
            raise ValueError("parameter statistics: mean and std must be finite, std positive for used parameters")
        return cls(list(names), mean, std, used)


def with_params(g_id: GraphsTuple, z, ok) -> GraphsTuple:
    """G_ID with its first P global columns replaced by standardized parameters ``z`` [N, P]
    where ``ok`` [N, P] is nonzero (``ParamStats.standardize``'s; arrays or tensors), GN_p's
    estimate elsewhere."""
    gl = g_id.globals
    z, ok = (torch.as_tensor(a, device=gl.device, dtype=gl.dtype) for a in (z, ok))
    P = z.shape[1]
    return g_id._replace(globals=torch.cat([torch.where(ok > 0, z, gl[:, :P]), gl[:, P:]], 1))


def param_stats(dataset) -> ParamStats:
    """The statistics of ``dataset``'s instance parameters (``static["params"]``, a parameterized
    dataset's) over the instances of its train split, NaN (a parameter an instance lacks) left
    out; a clear error if it has none."""
    names = list(dataset.meta.get("param_names", []))
    params = np.asarray(dataset.static["params"], dtype=np.float64)
    if not names or params.ndim != 2 or params.shape[1] != len(names):
        raise ValueError(f"dataset {dataset.system!r} has no instance parameters (param_loss needs a parameterized "
                         f"dataset: gnwarp generate --parameterized)")
    rows = np.ma.masked_invalid(params[np.unique(np.asarray(dataset["train"].instance[...]))])
    mean, std = rows.mean(0).filled(0.0), rows.std(0).filled(0.0)
    used = (rows.count(0) > 1) & (std > 1e-12 * np.maximum(1.0, np.abs(mean)))
    return ParamStats(names, mean, np.where(used, std, 1.0), used)


def estimate_params(g_id: GraphsTuple, stats: ParamStats) -> np.ndarray:
    """The physical parameters [N, P] that G_ID of a model trained with ``param_loss`` carries in
    its first P global columns (``stats``: ``param_stats`` of its training data); NaN for
    parameters that did not vary in training."""
    P = len(stats.names)
    if g_id.globals is None or g_id.globals.shape[-1] < P:
        raise ValueError(f"G_ID has {0 if g_id.globals is None else g_id.globals.shape[-1]} global columns; "
                         f"the {P} parameters need as many")
    z = g_id.globals[:, :P].detach().double().cpu().numpy()
    return np.where(stats.used, z * stats.std + stats.mean, np.nan)
