"""The settings of a reinforcement-learning run (``RLConfig``), checked on construction; light to
import (no torch), so the command line builds its flags from them.

    >>> cfg = RLConfig(task="swimmer6", agent="svg1", out="runs/rl/svg1-s0", seed=0)
"""
from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Literal

from gnwarp.rl.settings import AgentSettings
from gnwarp.validation import (ConfigError, Count, Flag, FloatRange, PositiveFloat, PositiveInt, Seed, Widths,
                               check_fields, check_keys, described)

__all__ = ["RLConfig", "RESUMABLE", "MAX_RL_HORIZON", "CONFIG_FILE"]

MAX_RL_HORIZON = 5     # SVG(N) runs accept N <= this (the paper's SVG(5+) did no better)
CONFIG_FILE = "config.json"
# keys a resumed run may change; the others must equal the folder's config.json
RESUMABLE = ("env_steps", "chunk", "budget_seconds", "progress", "device", "tensorboard", "cuda_graph",
             "torch_compile", "video_episodes", "video_steps", "renderer", "sim_threads")
# AgentSettings keys the run sets itself
_RUN_AGENT_KEYS = ("agent", "preset", "seed", "updates_per_step", "act_ahead")


@dataclasses.dataclass
class RLConfig:
    """A training run of one agent on one task, in the folder ``out`` (resumed where it holds one).

    ``task``: a task name (``gnwarp.control.TASKS``; "swimmer6" is dmc-swimmer-swimmer6).
    ``agent``: "ddpg", "svg0" or "svg1" .. "svg5". ``preset``: "spinningup" or "paper"
    (``gnwarp.rl.settings.PRESETS``). ``networks``: "mlp" or "gn" (graph networks on the
    observation graph, ``gnwarp.rl.gn_nets``; needs ``observation="dmc"``). ``observation``:
    "dmc" (the suite's observation, ``gnwarp.rl.observations.DMCObservation``) or "bodies" (the
    vector env's body-state layout). ``num_envs``: training episodes stepped together.
    ``episode_steps``: the time limit (None: the task's). ``env_steps``: env steps to train in
    all (control steps summed over envs; rounded up to whole rounds of ``num_envs`` episodes).
    ``utd``: gradient updates per env step. ``act_ahead``: the next action is picked before the
    step's updates, so that with the agent on CUDA and the true simulator on the CPU (``backend``
    "mujoco") the CPU steps the environment while the GPU updates (a simulator on the GPU gains
    nothing); the policy acts one step's updates behind (``AgentSettings.act_ahead``). ``update_after``, ``start_steps``, ``batch_size``,
    ``hidden``: as ``AgentSettings`` (None: its default / the preset's). ``latent``, ``blocks``:
    the GN networks' sizes; ``gn_impl``: their blocks on the Warp kernels or the torch reference. ``model_hidden``: the SVG(N) model's MLP widths (None: ``hidden`` for
    "mlp", (64,) for "gn"). ``buffer_size``: replay capacity in transitions. ``eval_every``:
    evaluate at the first episode end at or past each multiple of this many env steps (and
    before training, and at the end); ``eval_episodes``: deterministic-policy episodes, batched
    in a separate vector env, from the initial states of ``eval_seed`` (None: the run's ``seed``;
    the same for runs to compare: on swimmer6 the returns are bimodal by the target's distance,
    and which targets a seed's evaluation draws is half or more of the spread between seeds,
    ``bench/results/rl/README.md``). ``agent_settings``: further ``AgentSettings`` keys (gamma, q_lr,
    ...). ``seed``: of the networks, the agent, the env and the evaluation. ``device``: the
    agent's; ``backend``: the true simulator's ("auto": MuJoCo C where the run acts ahead or no
    GPU is, MuJoCo-Warp otherwise; the choice is saved with the run, ``gnwarp.rl.run_folder.run_backend``). ``chunk``: env steps at most in this call;
    ``budget_seconds``: stop before a round expected to end past this many seconds of this
    call, the call's end (final checkpoint, video) counted; both stop at episode ends only, so a
    resumed run equals an uninterrupted one.
    ``sim_threads``: the threads of MuJoCo C's rollout pool in each env (results do not depend on
    it; several runs side by side want few each). ``cuda_graph``: on CUDA, the gradient update is
    recorded once in a CUDA graph and replayed
    (``gnwarp.rl.graphed.Updater``; the same numbers as eager updates, several times faster).
    ``torch_compile``: the update's losses compiled (``Agent.compile_update``; "none": eager;
    "auto": "inductor" for MLP networks on CUDA where Triton imports, eager elsewhere, and eager
    with a warning if compiling fails; ``compile_backend``).
    ``video_episodes``, ``video_steps``, ``renderer``: at the end of a call that evaluated, a GIF
    ``video.gif`` of the first ``video_steps`` steps of that many episodes of its last evaluation
    (the deterministic policy on the true simulator; ``gnwarp.eval.animate_system``).
    """
    task: str = described("swimmer6", "task name (gnwarp.control.TASKS; swimmer6 = dmc-swimmer-swimmer6)")
    out: str = described("runs/rl", "the run folder (resumed where it holds a run)")
    agent: str = described("svg1", "ddpg, svg0 or svg1 .. svg5")
    preset: Literal["spinningup", "paper"] = described("spinningup", "preset of the agent's free values")
    networks: Literal["mlp", "gn"] = described("mlp", "policy, Q-function and model: MLPs or graph networks")
    observation: Literal["dmc", "bodies"] = described("dmc", "the suite's observation or the env's body states")
    num_envs: PositiveInt = described(10, "training episodes stepped together")
    episode_steps: PositiveInt | None = described(None, "time limit in control steps (unset: the task's)")
    env_steps: PositiveInt = described(1_000_000, "env steps to train in all (a resumed run goes on to this many)")
    utd: FloatRange(gt=0.0, le=1000.0) = described(1.0, "gradient updates per env step (at most 1000)")
    act_ahead: Flag = described(False, "pick the next action before the step's updates: a CPU simulator steps "
                                       "while the GPU updates (the policy acts one step's updates behind)")
    update_after: Count | None = described(None, "env steps before the first update (unset: 1000)")
    start_steps: Count | None = described(None, "env steps of uniform random actions (unset: the preset's)")
    batch_size: PositiveInt | None = described(None, "transitions per update (unset: the preset's)")
    hidden: Widths | None = described(None, "MLP widths (unset: the preset's for mlp, (64,) in GN blocks)")
    latent: PositiveInt = described(64, "GN latent width")
    blocks: PositiveInt = described(2, "GN blocks per network")
    gn_impl: Literal["warp", "torch"] = described("warp", "GN blocks on the Warp kernels or the torch reference")
    model_hidden: Widths | None = described(None, "SVG(N) model MLP widths (unset: hidden, (64,) for gn)")
    buffer_size: PositiveInt = described(1_000_000, "replay buffer capacity in transitions")
    eval_every: PositiveInt = described(10_000, "env steps between evaluations")
    eval_episodes: PositiveInt = described(20, "deterministic evaluation episodes, batched")
    eval_seed: Seed | None = described(None, "seed of the evaluation's initial states (unset: the run's seed; "
                                             "runs that share it evaluate on the same states)")
    agent_settings: dict = field(default_factory=dict)
    seed: Seed = described(0, "seed of networks, agent, envs and evaluation")
    device: Literal["auto", "cpu", "cuda"] = described("auto", "the agent's device")
    backend: Literal["auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu"] = described(
        "auto", "true simulator (auto: MuJoCo C acting ahead or without a GPU, else MuJoCo-Warp; saved in the "
                "run's config, kept on resume)")
    sim_threads: PositiveInt | None = described(
        None, "MuJoCo C's threads stepping the envs (unset: one per env up to the CPU count; few where runs go "
              "side by side: bench/rl_seeds.py sets its --threads; other backends ignore it)")
    chunk: PositiveInt | None = described(None, "env steps at most in this call (rounded up to whole episodes)")
    budget_seconds: PositiveFloat | None = described(None, "stop before a round expected to end past this many "
                                                           "seconds of this call")
    tensorboard: Flag = described(True, "TensorBoard logs where torch.utils.tensorboard imports")
    cuda_graph: Flag = described(True, "on CUDA, record the gradient update in a CUDA graph and replay it")
    torch_compile: Literal["auto", "none", "inductor", "aot_eager"] = described(
        "auto", "compile the update's losses with torch.compile (inductor: fused kernels; the second update "
                "compiles; rounding may differ from eager updates; auto: inductor for MLPs on CUDA, else none)")
    video_episodes: Count = described(2, "episodes of the call's last evaluation in video.gif (0: no video)")
    video_steps: PositiveInt = described(300, "control steps of each episode in the video")
    renderer: Literal["auto", "mujoco", "matplotlib"] = described(
        "auto", "the video's renderer (auto: MuJoCo's where OpenGL works, else matplotlib)")
    progress: Flag = described(True, "progress bar")

    def __post_init__(self):
        check_fields(self)
        if not all(isinstance(k, str) for k in self.agent_settings):
            raise ConfigError("agent_settings", "must be a table with string keys")
        given = sorted(set(self.agent_settings) & set(_RUN_AGENT_KEYS + ("hidden", "batch_size", "start_steps",
                                                                         "update_after")))
        if given:
            raise ConfigError(f"agent_settings.{given[0]}", "is a key of the run's own (set it without agent_settings.)")
        settings = self.agent_config()          # an unknown agent or N < 0 refused here
        self.agent = settings.agent
        if settings.horizon > MAX_RL_HORIZON:
            raise ConfigError("agent", f"runs take svg0 .. svg{MAX_RL_HORIZON} (and ddpg), got {self.agent}")
        if self.networks == "gn" and self.observation != "dmc":
            raise ConfigError("networks", "gn networks read the observation graph of the suite's observation: "
                                          "set observation to dmc")
        if settings.horizon >= 1 and self.observation != "dmc":
            raise ConfigError("observation", f"{self.agent} scores predicted observations with the task's "
                                             "ObservationReward, which reads the suite's observation: set it to dmc")

    def agent_config(self) -> AgentSettings:
        """The ``AgentSettings`` of this run (``ConfigError`` naming a refused key)."""
        extra = {k: v for k, v in (("hidden", self.hidden), ("batch_size", self.batch_size),
                                   ("start_steps", self.start_steps), ("update_after", self.update_after))
                 if v is not None}
        try:
            return AgentSettings(**{**self.agent_settings, **extra, "agent": self.agent, "preset": self.preset,
                                    "seed": self.seed, "updates_per_step": self.utd,
                                    "act_ahead": self.act_ahead})
        except TypeError as e:
            raise ConfigError("agent_settings", f"unknown AgentSettings key ({e})") from None
        except ConfigError as e:   # named as the run's config spells it
            key = e.path.split(".")[0]
            if key in self.agent_settings:
                raise e.within("agent_settings") from None
            if key == "updates_per_step":
                raise ConfigError("utd", e.reason) from None
            raise

    @property
    def horizon(self) -> int:
        """SVG(N)'s N (0 for svg0 and ddpg)."""
        return 0 if self.agent == "ddpg" else int(self.agent[3:])

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "RLConfig":
        return cls(**check_keys(cls, d, "RL run config keys"))
