"""``FlatAdam``: Adam / AdamW with gradient-norm clipping over one flat parameter buffer, in
Warp kernels (``kernels/train/optim.py``): 2-3 launches per step whatever the number of tensors.

At construction the parameters are moved into one flat buffer (each ``p.data`` becomes a view
of it, so modules keep working unchanged) and every parameter gets ``p.main_grad``, a view of
one flat gradient buffer. The Warp implementation of ``GraphNetwork`` adds its parameter gradients
straight into ``main_grad`` (one launch per block instead of one tensor per parameter) and
leaves ``p.grad`` as None; gradients that other code leaves in ``p.grad`` are added into
``main_grad`` at ``step()``. Gradients accumulate until ``zero_grad()`` (one memset).

    opt = FlatAdam(model.parameters(), lr=1e-4, max_grad_norm=1.0)
    for batch in data:
        opt.zero_grad()
        loss(model, batch).backward()
        opt.step()                       # clip by the global norm, then Adam
        print(float(opt.grad_norm))      # the norm before clipping (a device scalar)

Create the optimizer after the model is on its device and in its dtype (``model.to(...)`` would
replace the views). ``torch.nn.utils.clip_grad_norm_`` does not see ``main_grad``: clip with
``max_grad_norm``. The step count and learning rate live on the device, so a captured CUDA
graph of a training step replays correct bias corrections; after changing ``lr`` (by hand or
by an LR scheduler) outside ``step()``'s own check, i.e. with a captured graph, call
``sync_lr()`` before the next replay.

``WeightAverage``: an exponential moving average of the weights (Polyak averaging), updated
after each step on the device (capturable), applied in the weights' place for validation and
checkpoints (``TrainConfig.ema``).
"""
from __future__ import annotations

import math
from contextlib import contextmanager

import torch

from gnwarp.gn.flat import flatten_parameters
from gnwarp.interop import WP_DTYPE, Launcher
from gnwarp.kernels.train import optim as K

__all__ = ["FlatAdam", "WeightAverage"]


class FlatAdam(torch.optim.Optimizer):
    """Adam (``decoupled_weight_decay=True``: AdamW) over one flat buffer, torch's update rule.

    Args:
        params: the parameters (one group; all of one float dtype, float32 or float64, on one
            device; each ``requires_grad``).
        lr, betas, eps, weight_decay: as ``torch.optim.Adam``.
        max_grad_norm: clip the gradients by their global 2-norm first (as
            ``torch.nn.utils.clip_grad_norm_(params, max_grad_norm)``); None: no clipping.
        check_finite: after computing the norm, raise ``FloatingPointError`` (with the
            parameters untouched) if any gradient is NaN or Inf. Costs one host sync per step,
            so it cannot run inside a captured CUDA graph.
    """

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-8, weight_decay: float = 0.0,
                 decoupled_weight_decay: bool = False, max_grad_norm: float | None = None, check_finite: bool = False):
        if not (isinstance(lr, float | int) and lr >= 0 and math.isfinite(lr)):
            raise ValueError(f"lr must be a finite number >= 0, got {lr!r}")
        if len(betas) != 2 or not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"betas must be two numbers in [0, 1), got {betas!r}")
        if not eps > 0:
            raise ValueError(f"eps must be > 0, got {eps!r}")
        if not weight_decay >= 0:
            raise ValueError(f"weight_decay must be >= 0, got {weight_decay!r}")
        if max_grad_norm is not None and not max_grad_norm > 0:
            raise ValueError(f"max_grad_norm must be > 0 or None, got {max_grad_norm!r}")
        super().__init__(params, dict(lr=float(lr), betas=tuple(float(b) for b in betas), eps=float(eps),
                                      weight_decay=float(weight_decay)))
        if len(self.param_groups) != 1:
            raise ValueError("FlatAdam takes one parameter group")
        self.decoupled = bool(decoupled_weight_decay)
        self.max_grad_norm = None if max_grad_norm is None else float(max_grad_norm)
        self.check_finite = bool(check_finite)
        ps = self.param_groups[0]["params"]
        dt, dev = ps[0].dtype, ps[0].device
        for k, p in enumerate(ps):
            if p.dtype not in (torch.float32, torch.float64):
                raise TypeError(f"parameter {k} has dtype {p.dtype}; FlatAdam takes float32 or float64")
            if p.dtype != dt or p.device != dev:
                raise ValueError(f"parameter {k} is {p.dtype} on {p.device}, parameter 0 {dt} on {dev}: "
                                 "FlatAdam needs one dtype and one device")
            if not p.requires_grad:
                raise ValueError(f"parameter {k} does not require grad")
            if p.is_sparse:
                raise TypeError(f"parameter {k} is sparse")
        self.flat, self.offsets = flatten_parameters(ps)
        total = self.numel = self.flat.numel()
        with torch.no_grad():
            self.grad_flat = torch.zeros(total, dtype=dt, device=dev)
            self.exp_avg = torch.zeros(total, dtype=dt, device=dev)
            self.exp_avg_sq = torch.zeros(total, dtype=dt, device=dev)
            self.scalars = torch.zeros(K.SCALARS, dtype=dt, device=dev)
            self.scalars[K.LR] = float(lr)
            for p, o in zip(ps, self.offsets):
                p.main_grad = self.grad_flat[o:o + p.numel()].view_as(p)
        self._lr_on_device = float(lr)
        self._wp_dtype = WP_DTYPE[dt]

    # -- gradients -----------------------------------------------------------------------------
    @property
    def grad_norm(self) -> torch.Tensor:
        """The global gradient norm of the last step, before clipping (0-d device tensor; valid
        when ``max_grad_norm`` or ``check_finite`` is set)."""
        return self.scalars[K.NORM]

    @property
    def step_count(self) -> int:
        return int(self.scalars[K.STEP].item())

    def zero_grad(self, set_to_none: bool = True):
        """Zero the flat gradient (one memset) and drop any ``p.grad``."""
        self.grad_flat.zero_()
        for p in self.param_groups[0]["params"]:
            p.grad = None

    @torch.no_grad()
    def fold_grads(self) -> torch.Tensor:
        """Add the gradients that code other than the Warp GN block left in ``p.grad`` into the
        flat gradient (and drop them); returns the flat gradient, every parameter's gradient in
        one buffer (what a distributed trainer all-reduces before ``step``)."""
        for p in self.param_groups[0]["params"]:
            if p.grad is not None:
                p.main_grad.add_(p.grad)
                p.grad = None
        return self.grad_flat

    def sync_lr(self):
        """Copy the group's ``lr`` to the device scalar the update reads (``step()`` does this
        itself when not capturing; call it before replaying a captured step after a change)."""
        lr = float(self.param_groups[0]["lr"])
        if lr != self._lr_on_device:
            self.scalars[K.LR].fill_(lr)
            self._lr_on_device = lr

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        group = self.param_groups[0]
        self.fold_grads()
        capturing = self.flat.is_cuda and torch.cuda.is_current_stream_capturing()
        if not capturing:
            self.sync_lr()
        launch = Launcher(self.flat)
        T = self._wp_dtype
        b1, b2 = group["betas"]
        norm = self.max_grad_norm is not None or self.check_finite
        if norm:
            bd = K.BLOCK if self.flat.is_cuda else 1
            blocks = max(1, min(1024, -(-self.numel // (bd * 8))))
            launch.tiled(K.sumsq_kernel(T), blocks, bd, self.grad_flat, self.numel, bd, blocks * bd, self.scalars)
        clip = self.max_grad_norm is not None
        launch(K.finalize_kernel(T, clip=clip), 1, self.scalars, b1, b2, self.max_grad_norm if clip else 0.0,
               self.scalars)
        if self.check_finite and not capturing:
            n = float(self.scalars[K.NORM].item())
            if not math.isfinite(n):
                self.scalars[K.STEP] -= 1  # the step did not happen
                raise FloatingPointError(f"FlatAdam: gradient norm is {n}: a gradient holds NaN or Inf "
                                         "(parameters left unchanged)")
        wd = group["weight_decay"]
        nt = K.adam_threads(self.numel)
        launch(K.adam_kernel(T, weight_decay=wd > 0, decoupled=self.decoupled), nt, self.flat, self.grad_flat,
               self.exp_avg, self.exp_avg_sq, self.scalars, self.numel, nt, b1, b2, group["eps"], wd,
               self.flat, self.exp_avg, self.exp_avg_sq)
        return loss

    # -- checkpoints ---------------------------------------------------------------------------
    def state_dict(self):
        g = self.param_groups[0]
        return {"format": "gnwarp.FlatAdam/1",
                "sizes": [p.numel() for p in g["params"]],
                "step": self.step_count,
                "exp_avg": self.exp_avg.detach().cpu().clone(),
                "exp_avg_sq": self.exp_avg_sq.detach().cpu().clone(),
                "param_groups": [{k: v for k, v in g.items() if k != "params"}],
                "decoupled_weight_decay": self.decoupled, "max_grad_norm": self.max_grad_norm}

    def load_state_dict(self, state):
        if not isinstance(state, dict) or state.get("format") != "gnwarp.FlatAdam/1":
            raise ValueError("not a FlatAdam state dict (expected format 'gnwarp.FlatAdam/1'; a torch.optim.Adam "
                             "state cannot be loaded into FlatAdam)")
        sizes = [p.numel() for p in self.param_groups[0]["params"]]
        if list(state["sizes"]) != sizes:
            raise ValueError(f"FlatAdam state is for {len(state['sizes'])} parameters of sizes "
                             f"{list(state['sizes'])[:6]}..., this optimizer has {len(sizes)} of sizes {sizes[:6]}...")
        for name in ("exp_avg", "exp_avg_sq"):
            t = state[name]
            if not isinstance(t, torch.Tensor) or t.shape != (self.numel,):
                raise ValueError(f"FlatAdam state {name!r}: expected a tensor of shape ({self.numel},)")
            if not torch.isfinite(t).all():
                raise ValueError(f"FlatAdam state {name!r} contains NaN or Inf")
        with torch.no_grad():
            self.exp_avg.copy_(state["exp_avg"])
            self.exp_avg_sq.copy_(state["exp_avg_sq"])
            self.scalars[K.STEP] = float(state["step"])
        g = self.param_groups[0]
        g.update({k: v for k, v in state["param_groups"][0].items() if k in ("lr", "betas", "eps", "weight_decay")})
        self.decoupled = bool(state.get("decoupled_weight_decay", self.decoupled))
        self.max_grad_norm = state.get("max_grad_norm", self.max_grad_norm)
        self.sync_lr()


class WeightAverage:
    """An exponential moving average of ``tensors`` (a model's parameters, or FlatAdam's one flat
    buffer): after the t-th ``update()``, ``average += (1 - d_t) * (tensor - average)`` with
    ``d_t = min(decay, (1 + t) / (10 + t))``, so that early averages follow the weights instead of
    remembering their initial values. The count lives on the device and ``update`` never syncs
    with the host, so a captured CUDA graph of a training step replays it.

    ``applied()`` puts the averages in the tensors' place (the weights back on exit): validate and
    save inside it. ``state_dict()``, taken inside ``applied()``, holds the live weights and the
    count; ``load_state_dict`` expects the tensors to hold the averages (a checkpoint's weights)
    and puts the live weights back.
    """

    FORMAT = "gnwarp.WeightAverage/1"

    def __init__(self, tensors, decay: float):
        if isinstance(decay, bool) or not (isinstance(decay, float | int) and 0 < decay < 1):
            raise ValueError(f"decay must be a number in (0, 1), got {decay!r}")
        self.tensors = list(tensors)
        if not self.tensors:
            raise ValueError("WeightAverage needs at least one tensor")
        self.decay = float(decay)
        t0 = self.tensors[0]
        with torch.no_grad():
            self.average = [t.detach().clone() for t in self.tensors]
            self.count = torch.zeros((), dtype=t0.dtype, device=t0.device)
        self._live: list[torch.Tensor] | None = None   # the weights while the averages are applied

    @torch.no_grad()
    def update(self) -> None:
        """Move the averages toward the tensors' current values (no host synchronization)."""
        if self._live is not None:
            raise RuntimeError("WeightAverage.update inside applied(): the tensors hold the averages")
        self.count.add_(1)
        w = 1 - torch.clamp((1 + self.count) / (10 + self.count), max=self.decay)
        for a, t in zip(self.average, self.tensors):
            a.lerp_(t, w.to(a.dtype))

    @contextmanager
    def applied(self):
        """The averages in the tensors' place, the weights put back on exit (nests as one)."""
        if self._live is not None:
            yield self
            return
        with torch.no_grad():
            self._live = [t.detach().clone() for t in self.tensors]
            for t, a in zip(self.tensors, self.average):
                t.copy_(a)
        try:
            yield self
        finally:
            with torch.no_grad():
                for t, w in zip(self.tensors, self._live):
                    t.copy_(w)
            self._live = None

    def state_dict(self) -> dict:
        """The count and the live weights (on the CPU), for a checkpoint whose model holds the
        averages: take it inside ``applied()``."""
        if self._live is None:
            raise RuntimeError("WeightAverage.state_dict outside applied(): the checkpoint's weights must be the "
                               "averages")
        return {"format": self.FORMAT, "count": int(self.count.item()),
                "weights": [w.detach().cpu().clone() for w in self._live]}

    @torch.no_grad()
    def load_state_dict(self, state: dict) -> None:
        """Resume: the tensors hold the averages (a checkpoint's weights); ``state`` (from
        ``state_dict``) brings back the live weights and the count. ``ValueError`` naming what
        does not fit."""
        count = self.restore_live(self.tensors, state, keep=self.average)
        self.count.fill_(count)

    @classmethod
    @torch.no_grad()
    def restore_live(cls, tensors, state: dict, keep=None) -> int:
        """Check ``state`` (``state_dict``'s) against ``tensors`` and copy its live weights into
        them, first copying the tensors' values (the averages a checkpoint's model holds) into
        ``keep`` when given; returns the state's count. A run resumed without averaging calls it
        alone. ``ValueError`` naming what does not fit; nothing is changed then."""
        tensors = list(tensors)
        if not isinstance(state, dict) or state.get("format") != cls.FORMAT:
            raise ValueError(f"not a WeightAverage state (expected format {cls.FORMAT!r})")
        count, weights = state.get("count"), state.get("weights")
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"WeightAverage state: count must be an integer >= 0, got {count!r}")
        if not isinstance(weights, list) or len(weights) != len(tensors):
            raise ValueError(f"WeightAverage state holds {len(weights) if isinstance(weights, list) else 'no'} "
                             f"weight tensors, this model {len(tensors)}")
        for k, (w, t) in enumerate(zip(weights, tensors)):
            if not isinstance(w, torch.Tensor) or w.shape != t.shape:
                raise ValueError(f"WeightAverage state: weights[{k}] should have shape {tuple(t.shape)}, got "
                                 f"{tuple(w.shape) if isinstance(w, torch.Tensor) else type(w).__name__}")
            if not torch.isfinite(w).all():
                raise ValueError(f"WeightAverage state: weights[{k}] contains NaN or Inf")
        for a, t in zip(keep or (), tensors):
            a.copy_(t)
        for t, w in zip(tensors, weights):
            t.copy_(w)
        return count
