"""A replay buffer of vector-environment transitions on torch: a fixed-capacity ring on one device,
filled a step of all envs at a time, sampled uniformly as single transitions or as sequences that
never cross an episode's end (SVG(N)'s and a model's multi-step data).

    >>> buf = ReplayBuffer(100_000, obs_dim=13, action_dim=1, num_envs=4)
    >>> buf.add(obs, action, reward, next_obs, terminated, truncated)   # [4, 13], [4, 1], [4] ...
    >>> batch = buf.sample(256, generator)                              # Transitions, [256, ...]
    >>> seq = buf.sample_sequences(256, 3, generator)                   # [256, 3, ...]
"""
from __future__ import annotations

import dataclasses
import hashlib
import re

import numpy as np
import torch

__all__ = ["ReplayBuffer", "Transitions", "ReplayError", "reached_obs"]


class ReplayError(ValueError):
    """A refused replay-buffer call: shapes, dtypes, non-finite values, sampling beyond what is stored."""


@dataclasses.dataclass
class Transitions:
    """A batch of transitions: ``obs`` / ``next_obs`` [..., D], ``action`` [..., U], ``reward``,
    ``terminated``, ``truncated`` [...] (bool). ``next_obs`` is the observation the step reached,
    the episode's last one at a truncation (not the next episode's first). Leading shape [B] from
    ``sample``, [B, L] from ``sample_sequences`` (``next_obs[:, k] == obs[:, k + 1]``)."""
    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor

    def __len__(self) -> int:
        return self.obs.shape[0]


def reached_obs(next_obs, infos: dict):
    """The observations a vector env's step reached [E, D]: ``next_obs`` [E, D] with the rows that
    ended an episode replaced by ``infos["final_obs"]`` (Gymnasium's "same_step" autoreset, where
    ``next_obs`` holds the next episode's first observation there). NumPy or torch, as given."""
    if "final_obs" not in infos:
        return next_obs
    ended, final = infos["_final_obs"], infos["final_obs"]
    if isinstance(next_obs, torch.Tensor):
        ended = torch.as_tensor(ended, device=next_obs.device)
        return torch.where(ended[:, None], torch.as_tensor(final, device=next_obs.device), next_obs)
    return np.where(np.asarray(ended)[:, None], final, next_obs)


_FIELDS = ("obs", "action", "reward", "next_obs", "terminated", "truncated")


def _same_device(a: torch.device, b: torch.device) -> bool:
    """Whether two devices are one ("cuda" is the current CUDA device)."""
    def index(d):
        return torch.cuda.current_device() if d.type == "cuda" and d.index is None else d.index
    return a.type == b.type and index(a) == index(b)


class ReplayBuffer:
    """``capacity`` transitions (rounded down to a multiple of ``num_envs``) of ``num_envs`` envs
    stepped together, stored per env in time order ([capacity // num_envs, num_envs, ...] rings,
    so a sequence is contiguous rows of one env); the oldest step of all envs is overwritten
    first. ``dtype`` of observations, actions and rewards; ``device`` where everything lives.
    ``check_finite``: refuse NaN / Inf in ``add`` (one host sync per call)."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, num_envs: int = 1, device="cpu",
                 dtype: torch.dtype = torch.float32, check_finite: bool = True):
        for name, v, lo in (("capacity", capacity, 1), ("obs_dim", obs_dim, 1), ("action_dim", action_dim, 1),
                            ("num_envs", num_envs, 1)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ReplayError(f"{name} must be an integer >= {lo}, got {v!r}")
        if capacity < num_envs:
            raise ReplayError(f"capacity {capacity} holds less than one step of {num_envs} envs")
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise ReplayError(f"dtype must be a torch floating dtype, got {dtype!r}")
        self.num_envs, self.obs_dim, self.action_dim = int(num_envs), int(obs_dim), int(action_dim)
        self.rows = int(capacity) // self.num_envs          # time steps kept per env
        self.device, self.dtype, self.check_finite = torch.device(device), dtype, check_finite
        T, E = self.rows, self.num_envs
        z = dict(device=self.device)
        self.obs = torch.zeros(T, E, obs_dim, dtype=dtype, **z)
        self.action = torch.zeros(T, E, action_dim, dtype=dtype, **z)
        self.reward = torch.zeros(T, E, dtype=dtype, **z)
        self.next_obs = torch.zeros(T, E, obs_dim, dtype=dtype, **z)
        self.terminated = torch.zeros(T, E, dtype=torch.bool, **z)
        self.truncated = torch.zeros(T, E, dtype=torch.bool, **z)
        self.ptr = 0      # the row the next add writes
        self.filled = 0   # rows holding data (<= rows)
        self.added = 0    # steps added in all (transitions: added x num_envs)
        self._starts = None   # (length, added, ptr), cumulative count of valid starts, their number
        # set by loading an actions-only state: the digest the rebuilt buffer must have (gnwarp.rl.slim)
        self.pending_digest: str | None = None

    @property
    def capacity(self) -> int:
        return self.rows * self.num_envs

    def __len__(self) -> int:
        """Transitions stored."""
        return self.filled * self.num_envs

    # -- adding ---------------------------------------------------------------------------------
    def _values(self, name: str, v, shape: tuple, envs: int, flag: bool = False) -> torch.Tensor:
        """``v`` checked against ``shape`` (its envs' axis ``envs``) and moved to the buffer's device."""
        if isinstance(v, np.ndarray) or np.isscalar(v) or isinstance(v, (list, tuple)):
            v = torch.as_tensor(np.asarray(v))
        if not isinstance(v, torch.Tensor):
            raise ReplayError(f"{name} must be a tensor or array, got {type(v).__name__}")
        if tuple(v.shape) != shape:
            raise ReplayError(f"{name} has shape {tuple(v.shape)}; expected {shape} "
                              f"(num_envs={self.num_envs}, obs_dim={self.obs_dim}, action_dim={self.action_dim})")
        if flag:
            if v.dtype != torch.bool:
                raise ReplayError(f"{name} must be boolean, got {v.dtype}")
            return v.to(self.device)
        if v.dtype == torch.bool or v.is_complex() or not (v.is_floating_point() or v.dtype in (
                torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)):
            raise ReplayError(f"{name} must hold real numbers, got {v.dtype}")
        v = v.to(self.device, self.dtype)
        if self.check_finite and not bool(torch.isfinite(v).all()):
            bad = (~torch.isfinite(v)).movedim(envs, 0).reshape(self.num_envs, -1).any(-1).nonzero().flatten().tolist()
            raise ReplayError(f"{name} has NaN or Inf values (envs {bad})")
        return v

    def add(self, obs, action, reward, next_obs, terminated, truncated) -> None:
        """Store one step of every env: ``obs`` / ``next_obs`` [E, D], ``action`` [E, U], ``reward``
        [E], ``terminated`` / ``truncated`` [E] bool (tensors on any device or NumPy arrays).
        ``next_obs`` must be the step's own final observation where it ends an episode (a vector
        env's ``infos["final_obs"]`` in "same_step" autoreset); under "next_step" autoreset, skip
        the reset step's transition."""
        self._write(self.ptr, (), obs, action, reward, next_obs, terminated, truncated)
        self.ptr = (self.ptr + 1) % self.rows
        self.filled = min(self.filled + 1, self.rows)
        self.added += 1

    def put_rows(self, rows, obs, action, reward, next_obs, terminated, truncated) -> None:
        """Write ``len(rows)`` steps of every env into ring rows ``rows`` at once: values with a
        leading axis of that length (``obs`` [n, E, D], ...), checked as ``add`` checks them,
        leaving the counters (a rebuild, ``gnwarp.rl.slim.rebuild_buffer``, writes a round so)."""
        rows = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        if rows.ndim != 1 or not bool(((rows >= 0) & (rows < self.rows)).all()):
            raise ReplayError(f"rows must be a list of ring rows in [0, {self.rows}), got {rows.tolist()}")
        self._write(rows, (len(rows),), obs, action, reward, next_obs, terminated, truncated)

    def _write(self, index, lead: tuple, *values) -> None:
        E, D, U = self.num_envs, self.obs_dim, self.action_dim
        shapes = ((E, D), (E, U), (E,), (E, D), (E,), (E,))
        vals = [self._values(name, v, lead + shape, len(lead), flag=name in ("terminated", "truncated"))
                for name, v, shape in zip(_FIELDS, values, shapes)]
        for name, v in zip(_FIELDS, vals):
            getattr(self, name)[index] = v
        self._starts = None

    def _check_rebuilt(self) -> None:
        """Refuse to read or save a buffer that holds its actions only (loaded from a slim checkpoint)."""
        if self.pending_digest is not None:
            raise ReplayError("the replay buffer holds its actions only (a slim checkpoint): rebuild it first "
                              "(gnwarp.rl.slim.rebuild_buffer; run_rl does on resuming)")

    # -- sampling -------------------------------------------------------------------------------
    def _check_batch(self, batch: int, generator) -> None:
        if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 1:
            raise ReplayError(f"batch must be an integer >= 1, got {batch!r}")
        if generator is not None and not _same_device(generator.device, self.device):
            raise ReplayError(f"the generator is on {generator.device}; the buffer on {self.device}")
        if self.filled == 0:
            raise ReplayError("the replay buffer is empty: add transitions before sampling")
        self._check_rebuilt()

    def gather(self, rows: torch.Tensor, envs: torch.Tensor) -> Transitions:
        """The stored transitions at ``rows`` (ring rows) and ``envs`` (any equal shapes, from
        ``sample_index`` or ``sequence_index``): ``Transitions`` of that shape. No host sync, so a
        CUDA graph may record it with the indices in static tensors."""
        self._check_rebuilt()
        return Transitions(*(getattr(self, name)[rows, envs] for name in _FIELDS))

    def sample_index(self, batch: int, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows, envs) [batch] of ``batch`` transitions drawn uniformly with replacement from those
        stored: what ``sample`` gathers."""
        self._check_batch(batch, generator)
        i = torch.randint(0, self.filled * self.num_envs, (batch,), generator=generator, device=self.device)
        return i // self.num_envs, i % self.num_envs

    def sample(self, batch: int, generator: torch.Generator | None = None) -> Transitions:
        """``batch`` transitions drawn uniformly with replacement from those stored (``generator``
        on the buffer's device; None: torch's default). Returns ``Transitions`` of shape [batch]."""
        return self.gather(*self.sample_index(batch, generator))

    def valid_starts(self, length: int) -> torch.Tensor:
        """[filled, E] bool, in time order from the oldest stored step: True where a sequence of
        ``length`` steps starting there is stored and no step but its last ends an episode."""
        n = self.filled
        order = (self.ptr - n + torch.arange(n, device=self.device)) % self.rows   # oldest first
        ok = torch.zeros(n, self.num_envs, dtype=torch.bool, device=self.device)
        if length > n:
            return ok
        done = (self.terminated | self.truncated)[order]
        # a start s is valid when steps s .. s + length - 2 hold no episode end
        c = torch.cat([torch.zeros(1, self.num_envs, dtype=torch.int64, device=self.device),
                       done.long().cumsum(0)])
        m = n - length + 1
        ok[:m] = (c[length - 1:length - 1 + m] - c[:m]) == 0
        return ok

    def sequence_index(self, batch: int, length: int,
                       generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows, envs) [batch, length] of ``batch`` sequences drawn as ``sample_sequences`` draws
        them: what it gathers."""
        self._check_batch(batch, generator)
        if isinstance(length, bool) or not isinstance(length, (int, np.integer)) or length < 1:
            raise ReplayError(f"length must be an integer >= 1, got {length!r}")
        if length > self.filled:
            raise ReplayError(f"sequences of {length} steps need {length} stored steps per env; "
                              f"{self.filled} are stored")
        key = (length, self.added, self.ptr)
        if self._starts is None or self._starts[0] != key:   # the valid starts change only with add
            c = self.valid_starts(length).flatten().long().cumsum(0)
            self._starts = (key, c, int(c[-1]))
        _, c, total = self._starts
        if total == 0:
            raise ReplayError(f"no stored sequence of {length} steps lies within one episode")
        u = torch.randint(0, total, (batch,), generator=generator, device=self.device)
        flat = torch.searchsorted(c, u, right=True)        # the (u+1)-th valid start
        start, env = flat // self.num_envs, flat % self.num_envs
        rows = (self.ptr - self.filled + start[:, None] + torch.arange(length, device=self.device)) % self.rows
        return rows, env[:, None].expand(-1, length)

    def sample_sequences(self, batch: int, length: int, generator: torch.Generator | None = None) -> Transitions:
        """``batch`` sequences of ``length`` consecutive steps of one env, drawn uniformly with
        replacement among those within one episode (only the last step may end it). Returns
        ``Transitions`` of shape [batch, length]. The valid starts are counted once per ``add`` (one
        host sync, to refuse a buffer with no such sequence) and reused by later calls."""
        return self.gather(*self.sequence_index(batch, length, generator))

    # -- saving ---------------------------------------------------------------------------------
    def digest(self) -> str:
        """SHA-256 (hex) of the counters and every ring's filled rows (their bytes on the host, in
        ring order): what a buffer rebuilt from its actions must give again."""
        if self.pending_digest is not None:
            raise ReplayError("the replay buffer holds its actions only: it has no digest of its own until rebuilt")
        h = hashlib.sha256(f"{self.ptr},{self.filled},{self.added},{self.dtype}".encode())
        for name in _FIELDS:
            h.update(getattr(self, name)[:self.filled].cpu().contiguous().numpy().tobytes())
        return h.hexdigest()

    def state_dict(self, actions_only: bool = False) -> dict:
        """Everything needed to resume exactly: the rings' filled rows (tensors; the rows past
        them were never written) and the counters. ``actions_only``: the actions alone and the
        whole buffer's ``digest`` (a slim checkpoint, ``gnwarp.rl.slim``: the rest is rebuilt by
        re-simulating the actions)."""
        self._check_rebuilt()
        n = self.filled   # copied to the host (a GPU buffer's copy takes no device memory)
        names = ("action",) if actions_only else _FIELDS
        d = {name: getattr(self, name)[:n].to("cpu", copy=True) for name in names}
        d.update(ptr=self.ptr, filled=self.filled, added=self.added, rows=self.rows, num_envs=self.num_envs,
                 obs_dim=self.obs_dim, action_dim=self.action_dim)
        if actions_only:
            d.update(actions_only=True, digest=self.digest())
        return d

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()``'s contents; a buffer of other sizes is refused."""
        for key in ("num_envs", "obs_dim", "action_dim", "rows"):
            if int(state[key]) != getattr(self, key):
                raise ReplayError(f"the saved buffer has {key}={state[key]}; this one {getattr(self, key)}")
        n, ptr, added = int(state["filled"]), int(state["ptr"]), int(state["added"])
        if not (0 <= n <= self.rows and 0 <= ptr < self.rows and n == min(added, self.rows)
                and (n == self.rows or ptr == n)):
            raise ReplayError(f"the saved buffer's counters are inconsistent (filled={n}, ptr={ptr}, added={added}, "
                              f"{self.rows} rows): a damaged checkpoint")
        slim = bool(state.get("actions_only", False))
        digest = state.get("digest") if slim else None
        if slim and not (isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{64}", digest)):
            raise ReplayError("the saved buffer holds actions only but no valid digest of the rest: a damaged "
                              "checkpoint")
        names = ("action",) if slim else _FIELDS
        for name in names:   # every saved ring checked before any is written
            ring, saved = getattr(self, name), state[name]
            if saved.shape[0] not in (n, self.rows) or saved.shape[1:] != ring.shape[1:]:
                raise ReplayError(f"the saved buffer's {name} has shape {tuple(saved.shape)}; expected "
                                  f"{(n,) + tuple(ring.shape[1:])} ({n} filled rows)")
        for name in _FIELDS:
            ring = getattr(self, name)
            ring.zero_()
            if name in names:
                ring[:n].copy_(state[name][:n])
        self.ptr, self.filled, self.added = ptr, n, added
        self._starts = None
        self.pending_digest = digest
