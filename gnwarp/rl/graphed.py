"""The agents' gradient updates from a replay buffer, recorded once in a CUDA graph and replayed
(``Updater``): an update of small networks is some hundred kernel launches, so eager updates
are bound by launching, not by the GPU.

    >>> up = Updater(agent, buffer, generator)          # capture: auto (on CUDA)
    >>> metrics = up.run(10)                            # 10 updates; the last one's losses

Each update draws its randomness eagerly, before the recorded work: the batch's buffer indices
(from ``generator``, as ``ReplayBuffer.sample`` draws them) and the agent's noise (from its
generator), into static tensors; the recorded part gathers the batch from the buffer's rings
(fixed storage) and runs ``agent.update_step``. Uncaptured (the CPU, ``capture=False``) the same
draws and the same work run eagerly, so both modes give the same numbers and a run resumes
exactly in either. The first update runs eagerly (it creates the optimizers' state; an agent's
compiled losses, ``Agent.compile_update``, compile on the second, eagerly too); the next records
the graph (``gnwarp.interop.Graphed``, as the trainer and gradient MPC do). Loading the agent's state (``load_state_dict``: new optimizer
tensors) records it again.
"""
from __future__ import annotations

import warnings

import torch

from gnwarp.rl.agents import set_adam_mode
from gnwarp.rl.replay import ReplayBuffer

__all__ = ["Updater"]


class Updater:
    """Updates of ``agent`` on batches of ``batch_size`` from ``buffer`` (indices drawn with
    ``generator``); ``model_sequence``: SVG(N)'s model batch as sequences of that many steps
    (None: the update's batch). ``capture``: record the update in a CUDA graph (None: when the
    agent is on CUDA). ``captured`` tells whether a graph is in use; ``recordings`` counts them.
    A recording that fails (a network that syncs with the host) warns once, sets ``failure``
    and ``capture`` off, and the updates go on eagerly (nothing ran while recording)."""

    def __init__(self, agent, buffer: ReplayBuffer, generator: torch.Generator, model_sequence: int | None = None,
                 capture: bool | None = None):
        self.agent, self.buffer, self.generator = agent, buffer, generator
        if (buffer.obs_dim, buffer.action_dim) != (agent.obs_dim, agent.action_dim):
            raise ValueError(f"the buffer holds {buffer.obs_dim} observation and {buffer.action_dim} action "
                             f"features; the agent takes {agent.obs_dim} and {agent.action_dim}")
        if buffer.device.type != agent.device.type:
            raise ValueError(f"the buffer is on {buffer.device}, the agent on {agent.device}: put both on one device")
        if model_sequence is not None and (isinstance(model_sequence, bool) or not isinstance(model_sequence, int)
                                           or model_sequence < 1):
            raise ValueError(f"model_sequence must be None or an integer >= 1, got {model_sequence!r}")
        self.model_sequence = model_sequence
        on_cuda = agent.device.type == "cuda"
        if capture and not on_cuda:
            raise ValueError(f"capture=True needs the agent on CUDA; it is on {agent.device}")
        self.capture = on_cuda if capture is None else bool(capture)
        B = agent.settings.batch_size
        z = dict(dtype=torch.long, device=buffer.device)
        self.rows, self.envs = torch.zeros(B, **z), torch.zeros(B, **z)
        L = model_sequence
        self.seq_rows, self.seq_envs = (torch.zeros(B, L, **z), torch.zeros(B, L, **z)) if L else (None, None)
        shape = agent.update_noise_shape(B)
        self.noise = None if shape is None else torch.zeros(shape, dtype=agent.dtype, device=agent.device)
        self.recordings, self.failure = 0, None   # failure: why recording failed (then updates run eagerly)
        self._graphed, self._out, self._loads = None, {}, agent.loads

    @property
    def captured(self) -> bool:
        return self._graphed is not None and self._graphed.graph is not None

    def _draw(self) -> None:
        rows, envs = self.buffer.sample_index(self.rows.numel(), self.generator)
        self.rows.copy_(rows)
        self.envs.copy_(envs)
        if self.model_sequence:
            rows, envs = self.buffer.sequence_index(self.rows.numel(), self.model_sequence, self.generator)
            self.seq_rows.copy_(rows)
            self.seq_envs.copy_(envs)
        if self.noise is not None:
            self.noise.normal_(generator=self.agent.generator)

    def _work(self) -> dict[str, torch.Tensor]:
        batch = self.buffer.gather(self.rows, self.envs)
        model_batch = self.buffer.gather(self.seq_rows, self.seq_envs) if self.model_sequence else None
        return self.agent.update_step(batch, model_batch, self.noise)

    def _set_capturable(self, on: bool) -> None:
        """Adam's steps recordable (``on``) or eager (no warning about capturable eager steps)."""
        set_adam_mode(self.agent.optimizers(), capturable=on)

    def _graphed_step(self) -> None:
        self._out = self._work()   # eager: this update's losses; recording: the graph's output tensors

    def run(self, n: int) -> dict[str, torch.Tensor]:
        """``n`` updates; returns the last one's metrics (0-dim tensors; a captured update's are
        the graph's outputs, overwritten by the next replay), {} for n = 0."""
        from gnwarp.interop import Graphed   # one eager update on its side stream, then record, then replay
        metrics: dict[str, torch.Tensor] = {}
        if self.agent.loads != self._loads:       # the optimizers' tensors were replaced: record again
            self._graphed, self._loads = None, self.agent.loads
            if self.capture:
                self._set_capturable(False)
        for _ in range(int(n)):
            self._draw()
            if not self.capture:
                metrics = self._work()
            else:
                if self._graphed is None:   # compiled losses: one more, the compiling one, before recording
                    self._graphed = Graphed(self._graphed_step, warmup=2 if self.agent.compiled else 1)
                recording = self._graphed.graph is None and self._graphed.warmup == 0
                if recording:
                    self._set_capturable(True)
                try:
                    self._graphed()   # the warm-up runs the update; recording records it, then replays it
                except RuntimeError as e:   # a network that syncs with the host cannot be recorded
                    if not recording:
                        raise
                    self._give_up(e)
                    self._out = self._work()   # nothing ran while recording: this update, eagerly
                else:
                    self.recordings += int(recording)
                metrics = self._out
            self.agent.count_update()
        return metrics

    def _give_up(self, e: Exception) -> None:
        self._graphed, self.capture = None, False
        self._set_capturable(False)
        self.failure = f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0]}"
        warnings.warn(f"the update could not be recorded in a CUDA graph ({self.failure}); updating eagerly "
                      "from now on", RuntimeWarning, stacklevel=3)
