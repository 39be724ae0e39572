"""A training run's resumable copy without its replay buffer's observations, and the buffer rebuilt
from it: a run moved between machines (a lent GPU that keeps nothing between sessions) in the
size of its actions.

A run's checkpoint holds its whole replay buffer: on swimmer6 at 1M env steps 217 MB, of which
the actions are 20 MB (``bench/rl_slim.py``). Every round of a run starts
its episodes from seeded resets (``round_seed``) and the simulator is deterministic, so stepping
the stored actions again gives the stored transitions again. ``slim_run(run, dest)`` writes a
folder that ``run_rl`` resumes like the run: its checkpoint holds the agent, the loop's state, the
buffer's actions and the SHA-256 digest of the whole buffer; on resuming, ``rebuild_buffer``
re-simulates the buffer's rounds with the run's training env and refuses to go on unless the
rebuilt buffer has the saved digest (another MuJoCo build, backend or CPU may round differently).

    >>> slim_run("runs/rl/s0", "carry/s0")          # then, on the other machine:
    >>> run_rl(RLConfig(out="carry/s0", ...))         # rebuilds, checks, trains on
    gnwarp rl -o runs/rl/s0 --slim carry/s0
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Callable

import torch

from gnwarp.files import atomic_write
from gnwarp.rl.config import CONFIG_FILE, RLConfig
from gnwarp.rl.replay import ReplayBuffer, ReplayError, reached_obs
from gnwarp.rl.run_log import (CHECKPOINT, LOG_FILE, RECORDS_FILE, TIMING_FILE, RLCheckpointError, load_checkpoint,
                               save_checkpoint)

__all__ = ["slim_run", "rebuild_buffer", "COPIED_FILES"]

# the run's files a slim copy takes along (the checkpoint is rewritten; TensorBoard logs and the
# video stay behind)
COPIED_FILES = (RECORDS_FILE, LOG_FILE, TIMING_FILE)


def _buffer_of(state: dict) -> ReplayBuffer:
    """A CPU ``ReplayBuffer`` holding a checkpoint's (full) buffer state."""
    try:
        dtype = state["obs"].dtype
        buf = ReplayBuffer(int(state["rows"]) * int(state["num_envs"]), int(state["obs_dim"]),
                           int(state["action_dim"]), int(state["num_envs"]), dtype=dtype, check_finite=False)
    except (KeyError, AttributeError, TypeError) as e:
        raise RLCheckpointError(f"the checkpoint's replay buffer is malformed ({type(e).__name__}: {e})") from None
    buf.load_state_dict(state)
    return buf


def slim_run(run, dest) -> Path:
    """Write into folder ``dest`` (new, or empty) a copy of the run in folder ``run`` that
    ``run_rl`` resumes: ``checkpoint.pt`` with the replay buffer's actions and digest in place of
    the buffer (``ReplayBuffer.state_dict(actions_only=True)``), ``config.json`` (its ``out``
    naming ``dest``), and the records, progress log and timings. Returns ``dest``."""
    run, dest = Path(run), Path(dest)
    if not (run / CHECKPOINT).is_file() or not (run / CONFIG_FILE).is_file():
        raise FileNotFoundError(f"no gnwarp rl run in {run}: its {CHECKPOINT} or {CONFIG_FILE} is missing")
    if dest.exists() and (not dest.is_dir() or dest.resolve() == run.resolve() or any(dest.iterdir())):
        raise ValueError(f"slim_run writes into a new or empty folder, not {dest}")
    from gnwarp.validation import read_config_file
    cfg = read_config_file(run / CONFIG_FILE, "RLConfig keys")
    RLConfig.from_dict(cfg)   # a broken config fails here, not when the copy resumes
    ck = load_checkpoint(run / CHECKPOINT)
    if not isinstance(ck.get("buffer"), dict):
        raise RLCheckpointError(f"{run / CHECKPOINT} holds no replay buffer")
    if ck["buffer"].get("actions_only"):
        raise ValueError(f"{run} is a slim copy already: copy its folder as it is")
    buf = _buffer_of(ck["buffer"])
    T = (ck.get("env") or {}).get("episode_steps") if isinstance(ck.get("env"), dict) else None
    if not isinstance(T, int) or T < 1:
        raise RLCheckpointError(f"{run / CHECKPOINT} does not name its episodes' length (env.episode_steps)")
    _rounds_kept(buf, T)   # refused now, not on the other machine
    ck["buffer"] = buf.state_dict(actions_only=True)
    cfg["out"] = str(dest)
    if isinstance(ck.get("config"), dict):
        ck["config"]["out"] = str(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(dest, folder=True) as tmp:   # the whole folder or nothing
        for name in COPIED_FILES:
            if (run / name).is_file():
                shutil.copyfile(run / name, tmp / name)
        (tmp / CONFIG_FILE).write_text(json.dumps(cfg, indent=1) + "\n")
        save_checkpoint(tmp / CHECKPOINT, ck)
    return dest


def _rounds_kept(buffer: ReplayBuffer, T: int) -> range:
    """The rounds of ``T`` steps whose every step ``buffer`` keeps; ``ReplayError`` where it keeps
    part of one (a ring of rows not a multiple of ``T`` that has wrapped: the oldest round lost its
    first actions, so no copy of it can be rebuilt)."""
    added, filled = buffer.added, buffer.filled
    if added % T or (added - filled) % T:
        raise ReplayError(f"the replay buffer keeps {filled} of its {added} steps, not whole rounds of {T} steps "
                          f"(its ring of {buffer.rows} rows is not a multiple of the episode length, and it "
                          "wrapped): it cannot be rebuilt by re-simulating rounds. Copy the run's folder as it is")
    return range((added - filled) // T, added // T)


# a rebuild of fewer env steps runs in this process: starting worker processes costs seconds
IN_PROCESS_STEPS = 200_000


def _simulate_round(env, seed: int, actions: torch.Tensor, host: bool = False) -> dict:
    """One round re-simulated: ``env`` reset with ``seed`` (env i: seed + i) and stepped with
    ``actions`` [T, E, U]; its transitions as tensors [T, E, ...] where the env gives them, on the
    host with ``host`` (a worker's, to send back: copied once at the end, not a sync a step)."""
    obs, _ = env.reset(seed=seed)
    out = {k: [] for k in ("obs", "reward", "next_obs", "terminated", "truncated")}
    for a in actions:
        if isinstance(obs, torch.Tensor):
            sent = a.to(obs.device)
        else:
            sent = a.numpy()
        next_obs, reward, terminated, truncated, infos = env.step(sent)
        for k, v in (("obs", obs), ("reward", reward), ("next_obs", reached_obs(next_obs, infos)),
                     ("terminated", terminated), ("truncated", truncated)):
            out[k].append(torch.as_tensor(v))
        obs = next_obs
    return {k: torch.stack(v).cpu() if host else torch.stack(v) for k, v in out.items()}


_WORKER_ENV = None


def _start_worker(make_env) -> None:
    global _WORKER_ENV
    torch.set_num_threads(1)
    _WORKER_ENV = make_env()


def _simulate_in_worker(job: tuple) -> dict:
    return _simulate_round(_WORKER_ENV, *job, host=True)


def rebuild_buffer(buffer: ReplayBuffer, make_env: Callable[[], object], seed_of: Callable[[int], int],
                   episode_steps: int, workers: int | None = None, progress: bool = False) -> float:
    """Fill ``buffer`` (loaded from a slim checkpoint: its ``pending_digest`` set) by re-simulating
    its rounds: round r's ``num_envs`` episodes of ``episode_steps`` steps from
    ``env.reset(seed=seed_of(r))``, each step's action the stored one, each transition written to
    its ring row. ``make_env()``: the run's training env ("same_step" autoreset, ``num_envs``
    envs: the very shapes the run stepped, so that every operation rounds as it did).
    ``workers`` processes re-simulate rounds side by side, each with its own env (``make_env``
    then must pickle; they start as new interpreters, "spawn", which import the calling script:
    a script guards its own work with ``if __name__ == "__main__"``); None: one per core up to
    16, or this process alone below ``IN_PROCESS_STEPS`` env steps. An env on the GPU
    (MuJoCo-Warp) wants 1: one process holds the device. Raises ``ReplayError`` unless the rebuilt buffer has the
    saved digest (it is then left actions-only). Returns the seconds it took (0 where nothing
    was pending)."""
    digest = buffer.pending_digest
    if digest is None:
        return 0.0
    t0 = time.perf_counter()
    T, E, rows = int(episode_steps), buffer.num_envs, buffer.rows
    rounds = list(_rounds_kept(buffer, T))
    at = {r: [(r * T + t) % rows for t in range(T)] for r in rounds}
    jobs = [(seed_of(r), buffer.action[at[r]].cpu()) for r in rounds]
    if workers is None:
        import os
        workers = 1 if len(rounds) * T * E < IN_PROCESS_STEPS else min(16, os.cpu_count() or 1, len(rounds))
    from tqdm.auto import tqdm
    pending, buffer.pending_digest = digest, None
    try:
        with tqdm(total=len(rounds) * T * E, unit="step", unit_scale=True, desc="rebuilding the replay buffer",
                  disable=not progress, dynamic_ncols=True) as bar:
            def write(r: int, out: dict) -> None:   # a round at once: few copies to a GPU buffer
                buffer.put_rows(at[r], out["obs"], buffer.action[at[r]], out["reward"], out["next_obs"],
                                out["terminated"], out["truncated"])
                bar.update(T * E)
            if workers <= 1:
                env = make_env()
                try:
                    for r, job in zip(rounds, jobs):
                        write(r, _simulate_round(env, *job))
                finally:
                    env.close()
            else:
                import multiprocessing
                from concurrent.futures import ProcessPoolExecutor
                with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_start_worker, initargs=(make_env,)) as pool:
                    for r, out in zip(rounds, pool.map(_simulate_in_worker, jobs)):
                        write(r, out)
        got = buffer.digest()
    except BaseException:
        buffer.pending_digest = pending
        raise
    if got != pending:
        buffer.pending_digest = pending
        raise ReplayError(f"the rebuilt replay buffer differs from the saved one (digest {got[:12]} against "
                          f"{pending[:12]}): this simulator does not reproduce the run's steps bit for bit "
                          "(another MuJoCo build, backend or CPU?). Resume the full run where it was trained")
    return time.perf_counter() - t0
