"""A training step replayed from one CUDA graph.

Uncaptured, a training step of the paper core launches ~40 Warp kernels and ~100 torch ones from
Python, each costing tens of microseconds of host time: the loop is host-bound at a fraction of
the GPU's speed. Captured, the step's device work is recorded once (batch sampling on the
device, input noise, normalizer accumulation, loss, backward, clipping, the optimizer update,
the running loss sums) and replays it: one launch a step, no host synchronization inside.

``Trainer`` replays its step through ``gnwarp.interop.Graphed``. What must hold for a step to be
captured (``capture_problem`` says what does not): a CUDA device;
batches of one shape (graphs of one topology per dataset; mixed sizes need host-side masks);
an optimizer whose learning rate lives on the device (``FlatAdam``, or torch's Adam made
capturable with a tensor learning rate, as the ``Trainer`` makes it); a random generator the
graph can replay (the device's default generator, or any with
``CUDAGraph.register_generator_state``).
"""
from __future__ import annotations

import torch

__all__ = ["capture_problem", "registers_generators", "default_generator"]


def registers_generators() -> bool:
    """Whether this torch can replay random numbers of any generator in a CUDA graph."""
    return hasattr(torch.cuda.CUDAGraph, "register_generator_state")


def default_generator(device: torch.device) -> torch.Generator:
    """The default random generator of a CUDA device (CUDA graphs replay it by themselves)."""
    return torch.cuda.default_generators[device.index if device.index is not None else torch.cuda.current_device()]


def capture_problem(device: torch.device, static_shapes: bool, generator: torch.Generator) -> str | None:
    """None if a training step on ``device`` can be captured, else why not."""
    if device.type != "cuda":
        return "capture needs a CUDA device"
    if not static_shapes:
        return "the batches' graphs vary in size (several topologies in one dataset)"
    if generator is not default_generator(device) and not registers_generators():
        return "this torch cannot replay a non-default random generator in a CUDA graph"
    return None
