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
exactly in either. The first update runs eagerly (it creates the optimizers' state); the
second records the graph. Loading the agent's state (``load_state_dict``: new optimizer
tensors) records it again.
"""
from __future__ import annotations

import warnings

import torch

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
        self.graph, self.out, self.recordings = None, None, 0
        self.failure = None   # why recording failed (then updates run eagerly), else None
        self._stream = None   # the side stream of the eager update before recording and of the recording
        self._eager_done, self._loads = False, agent.loads

    @property
    def captured(self) -> bool:
        return self.graph is not None

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

    def _eager(self) -> dict[str, torch.Tensor]:
        if not self.capture:
            return self._work()
        # the update that precedes recording runs on the stream it records on (torch's recipe)
        if self._stream is None:
            self._stream = torch.cuda.Stream(self.agent.device)
        main = torch.cuda.current_stream(self.agent.device)
        self._stream.wait_stream(main)
        with torch.cuda.stream(self._stream):
            out = self._work()
        main.wait_stream(self._stream)
        return out

    def _record(self) -> None:
        from gnwarp.interop import cuda_graph     # Warp's launches recorded too (GN networks)
        for opt in self.agent.optimizers():       # Adam's step count on the device, its steps recordable
            for group in opt.param_groups:
                group["capturable"] = True
            for p, st in opt.state.items():
                if "step" in st:
                    st["step"] = st["step"].to(p.device, torch.float32)
        graph = torch.cuda.CUDAGraph()
        main = torch.cuda.current_stream(self.agent.device)
        self._stream.wait_stream(main)
        with cuda_graph(graph, self._stream):
            out = self._work()
        main.wait_stream(self._stream)
        self.graph, self.out = graph, out
        self.recordings += 1

    def run(self, n: int) -> dict[str, torch.Tensor]:
        """``n`` updates; returns the last one's metrics (0-dim tensors; a captured update's are
        the graph's outputs, overwritten by the next replay), {} for n = 0."""
        metrics: dict[str, torch.Tensor] = {}
        if self.agent.loads != self._loads:       # the optimizers' tensors were replaced
            self.graph, self._eager_done, self._loads = None, False, self.agent.loads
            if self.capture:
                for opt in self.agent.optimizers():   # eager again until recorded (no capturable warning)
                    for group in opt.param_groups:
                        group["capturable"] = False
        for _ in range(int(n)):
            self._draw()
            if self.graph is None and self.capture and self._eager_done:
                try:
                    self._record()   # records without computing: the replay below does the update
                except RuntimeError as e:   # a network that syncs with the host cannot be recorded
                    self.graph, self.capture = None, False
                    self.failure = f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0]}"
                    warnings.warn(f"the update could not be recorded in a CUDA graph ({self.failure}); "
                                  "updating eagerly from now on", RuntimeWarning, stacklevel=2)
            if self.graph is not None:
                self.graph.replay()
                metrics = self.out
            else:
                metrics = self._eager()
                self._eager_done = True
            self.agent.count_update()
        return metrics
