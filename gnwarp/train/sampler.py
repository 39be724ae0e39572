"""Training batches on the device: (input graphs, true next states) drawn uniformly over (sequence,
step) of each dataset's train split, several datasets mixed in equal proportion (D.7, D.8)."""
from __future__ import annotations

import numpy as np
import torch

from gnwarp.graphs import GraphsTuple, batch

__all__ = ["SplitSampler", "BatchSampler"]


class SplitSampler:
    """A dataset's train split on the device, with its graph builder in the model's layout."""

    def __init__(self, ds, model, device):
        sp = ds["train"]
        if len(sp) == 0 or sp.num_steps == 0:
            raise ValueError(f"dataset {ds.system!r} has an empty train split")
        dtype = model.dtype
        self.name = ds.system
        self.body = torch.as_tensor(np.asarray(sp.body[...]), device=device, dtype=dtype)
        self.ctrl = torch.as_tensor(np.asarray(sp.ctrl[...]), device=device, dtype=dtype)
        self.instance = torch.as_tensor(np.asarray(sp.instance[...]), device=device, dtype=torch.int64)
        self.builder = model.graph_builder(ds)
        self.S, self.T = self.body.shape[0], self.ctrl.shape[1]
        # one topology and every actuator slot's control present: one Warp launch writes a batch
        self.fused = self.builder.fuses(self.body, self.ctrl)

    def sample(self, n: int, gen: torch.Generator) -> tuple[GraphsTuple, torch.Tensor]:
        """(graph, target next states [sum(n_node), 13]) of n uniform (sequence, step) pairs."""
        dev = self.body.device
        seq = torch.randint(self.S, (n,), generator=gen, device=dev)
        t = torch.randint(self.T, (n,), generator=gen, device=dev)
        return self.builder.sequence_batch(self.instance, self.body, self.ctrl, seq, t, fused=self.fused)


class BatchSampler:
    """Batches from one or more datasets, in equal proportion within each batch."""

    def __init__(self, datasets, model, device):
        self.parts = [SplitSampler(d, model, device) for d in datasets]

    @property
    def static_shapes(self) -> bool:
        """Whether every batch has the same shapes (each dataset of one topology): then sampling
        needs no host-side mask and a training step can be captured."""
        return all(p.builder.uniform for p in self.parts)

    def sample(self, batch_size: int, gen: torch.Generator) -> tuple[GraphsTuple, torch.Tensor]:
        """(graph of ``batch_size`` graphs, target next states [sum(n_node), 13])."""
        k = len(self.parts)
        sizes = [batch_size // k + (1 if i < batch_size % k else 0) for i in range(k)]
        got = [p.sample(n, gen) for p, n in zip(self.parts, sizes) if n > 0]
        if len(got) == 1:
            return got[0]
        return batch([g for g, _ in got]), torch.cat([t for _, t in got], 0)
