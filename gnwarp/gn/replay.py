"""Record a rollout's GN blocks in its forward, replay them in its adjoint backward.

The adjoint loop (``gnwarp/models/rollout.py``) recomputes each step's forward before taking its
vector-Jacobian product. When no parameter wants a gradient (planning: gradients with respect to
controls and initial states only), a block's backward needs nothing of its forward but the ReLU
masks of its hidden layers and, where later code reads them, its outputs. An ``ActivationStore``
keeps exactly that per (step, block call): in the forward (``recording(t)``) each blas-path block
packs its masks to 1 bit per element and copies the outputs the model reads; in the backward
(``replaying(t)``) each block returns the stored outputs and hands the masks to its backward
instead of running its GEMMs again. The rest of the step (features, normalizers, the state update)
is recomputed under autograd as before.

Which outputs are kept: ``keep`` lists, per block call of a step, the outputs ("nodes", "edges",
"globals") the model reads after that block; the others replay as zeros. A model declares it
(``GNCore.replay_outputs``: only GN2's nodes, since GN1's outputs feed GN2 alone, which replays
too); without a declaration every output is kept. While a store is active every block runs on
the blas path, so every block of the step replays.

Memory: the masks and kept outputs of every step (for the paper core on 4096 cheetah graphs 33
MB a step, measured: 3.3 GB for 100 steps) in place of one step's activations; the engine drops the store when it would pass a
budget. Buffers are allocated at the first recording and reused after, so a CUDA-graph capture
of the recording and of the replay reads and writes fixed addresses.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import torch

from gnwarp.gn.mlp import pack_mask

__all__ = ["ActivationStore", "BlockSlot", "active_store", "OUTPUT_NAMES"]

OUTPUT_NAMES = ("nodes", "edges", "globals")

_ACTIVE: list = [None]   # the store of the step being recorded or replayed (one at a time)


def active_store():
    """The ``ActivationStore`` of the step running now, or None."""
    return _ACTIVE[0]


@dataclass
class BlockSlot:
    """What one block call of one step keeps: its kept outputs and its MLPs' packed ReLU masks
    ({"edge" | "node" | "global": [mask per hidden layer]})."""
    outputs: dict = field(default_factory=dict)
    masks: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        n = sum(t.numel() * t.element_size() for t in self.outputs.values())
        return n + sum(m.nbytes for ms in self.masks.values() for m in ms)


class ActivationStore:
    """Per-step, per-block-call records of a rollout of ``n_steps`` steps (see the module
    docstring). ``keep``: per block call of a step, the output names kept (None: all).

    ``generation`` counts completed recordings; a backward replays only the recording its forward
    made (``RolloutEngine`` checks). ``valid``: every step of the last recording is complete."""

    def __init__(self, n_steps: int, keep: list | None = None):
        self.slots: list[list[BlockSlot]] = [[] for _ in range(int(n_steps))]
        self.keep = keep
        self.mode: str | None = None
        self.t = 0
        self.k = 0
        self.generation = 0
        self.valid = False
        self.enabled = True
        self.sized = False   # the owner checked the first recording's size against its budget

    def kept(self, k: int) -> tuple:
        """The output names block call ``k`` of a step keeps."""
        if self.keep is None or k >= len(self.keep):
            return OUTPUT_NAMES
        return tuple(self.keep[k])

    @contextlib.contextmanager
    def _scope(self, t: int, mode: str):
        if _ACTIVE[0] is not None:
            raise RuntimeError("an activation store is already active (stores do not nest)")
        self.t, self.k, self.mode = int(t), 0, mode
        _ACTIVE[0] = self
        try:
            yield self
        finally:
            _ACTIVE[0] = None
            self.mode = None

    def recording(self, t: int):
        """Context of step ``t`` of a forward: its blocks record into the store."""
        return self._scope(t, "record")

    def replaying(self, t: int):
        """Context of step ``t`` of a backward: its blocks replay from the store."""
        if not self.valid:
            raise RuntimeError("the activation store holds no complete recording to replay")
        return self._scope(t, "replay")

    def take(self) -> tuple[BlockSlot, int] | None:
        """(slot, block call index) of the next block call of the current step; None when the
        store is disabled (the block then runs as usual)."""
        if not self.enabled:
            return None
        k = self.k
        self.k += 1
        row = self.slots[self.t]
        if k < len(row):
            return row[k], k
        if self.mode == "replay":
            raise RuntimeError(f"step {self.t} recorded {len(row)} block call(s); its replay made more")
        row.append(BlockSlot())
        return row[k], k

    def record(self, launch, slot: BlockSlot, k: int, outputs: dict, hidden: dict) -> None:
        """Keep block call ``k``'s outputs ({name: tensor or None}) that ``kept(k)`` names and
        pack its MLPs' hidden activations ({mlp: [activation per hidden layer]}) into ``slot``
        (into its existing buffers after the first recording)."""
        for name in self.kept(k):
            x = outputs.get(name)
            if x is None:
                continue
            if name in slot.outputs:
                slot.outputs[name].copy_(x)
            else:
                slot.outputs[name] = x.detach().clone()
        for mlp, acts in hidden.items():
            old = slot.masks.get(mlp)
            slot.masks[mlp] = [pack_mask(launch, a, None if old is None else old[i].bits) for i, a in enumerate(acts)]

    def step_bytes(self, t: int = 0) -> int:
        """Bytes step ``t`` holds."""
        return sum(s.nbytes for s in self.slots[t])

    def drop(self) -> None:
        """Free every buffer and record nothing more."""
        self.slots = [[] for _ in self.slots]
        self.enabled = False
        self.valid = False

    def output(self, slot: BlockSlot, name: str, shape: tuple, like: torch.Tensor) -> torch.Tensor:
        """A replayed output: a copy of the kept one, else zeros of ``shape`` (its values are read
        by nothing but blocks that replay too)."""
        x = slot.outputs.get(name)
        if x is None:
            return torch.zeros(shape, dtype=like.dtype, device=like.device)
        return x.clone()
