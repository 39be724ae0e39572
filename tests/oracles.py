"""Stand-in models for testing evaluation: their predictions are the data's true states."""
import numpy as np
import torch


class TruthModel:
    """An oracle "model" on a dataset's test split: one-step predictions are the true next states,
    rollouts the true trajectories (found by their initial states). ``diverge_at``: the first
    rollout turns NaN from that step on (what evaluation must report, not hide)."""
    training = False

    def __init__(self, ds, diverge_at: int | None = None):
        self.ds, self.diverge_at = ds, diverge_at

    def eval(self):
        return self

    def train(self, mode=True):
        return self

    def graph_builder(self, ds):
        return None

    def rollout(self, x0, ctrl, instance=None, builder=None):
        body = torch.as_tensor(np.asarray(self.ds["test"].body[...], dtype=np.float32))
        x0 = torch.as_tensor(x0, dtype=torch.float32)
        T = ctrl.shape[1]
        if T == 1:  # one step from a true state: find its (sequence, step)
            out = []
            for x in x0:
                s, t = np.argwhere((body == x).all(-1).all(-1).numpy())[0]
                out.append(body[s, t:t + 2])
            return torch.stack(out)
        idx = [int(np.flatnonzero((body[:, 0] == x).all(-1).all(-1))[0]) for x in x0]
        traj = body[idx, :T + 1].clone()
        if self.diverge_at is not None:
            traj[:1, self.diverge_at:] = float("nan")
        return traj
