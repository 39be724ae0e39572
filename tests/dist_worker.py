"""One rank of the distributed tests (tests/test_distributed.py starts two of these).

    python dist_worker.py train DATA OUT      # one training step per rank; rank 0 saves what it saw
    python dist_worker.py die DATA OUT        # rank 1 exits mid-training; rank 0 must fail clearly
"""
import json
import os
import sys

import torch

from gnwarp.train import TrainConfig
from gnwarp.train.trainer import Trainer

TINY = {"gn": {"latent": 16, "edge_hidden": [16], "node_hidden": [16], "global_hidden": [16]}}


def config(data, out, **kw):
    base = dict(data=[data], out=out, steps=1, batch_size=4, noise_std=0.0, normalizer_warmup=0, device="cpu",
                valid_every=1000, valid_sequences=2, progress=False, log_every=1, capture=False, model=TINY,
                optimizer="adam")
    base.update(kw)
    return TrainConfig.from_dict(base)


class Recorder:
    """The trainer's sampler, keeping each batch it hands out (and exiting on a given call)."""

    def __init__(self, inner, die_at=None):
        self.inner, self.batches, self.die_at = inner, [], die_at

    @property
    def static_shapes(self):
        return self.inner.static_shapes

    def sample(self, n, gen):
        if self.die_at is not None and len(self.batches) == self.die_at:
            os._exit(3)   # a rank dying without a word
        b = self.inner.sample(n, gen)
        self.batches.append(b)
        return b


def averaged_gradients(t) -> torch.Tensor:
    """The gradients the last step's update read, as one vector (over ranks: averaged)."""
    from gnwarp.train.optim import FlatAdam
    if isinstance(t.optimizer, FlatAdam):
        return t.optimizer.grad_flat.clone()
    return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in t.model.parameters()])


def main(what, data, out):
    if what == "train":
        t = Trainer(config(data, out, optimizer=os.environ.get("OPT", "adam"),
                           overlap_allreduce=os.environ.get("OVERLAP") == "1"))
        t.sampler = Recorder(t.sampler)
        t.run()
        g, target = t.sampler.batches[-1]
        # clones: the batch's tensors carry the builder's cached context as attributes
        mine = {"graph": {k: v.clone() for k, v in g._asdict().items() if isinstance(v, torch.Tensor)},
                "target": target.clone(), "rank": t.ranks.rank,
                "early_buckets": None if t.buckets is None else t.buckets.sent}
        got = t.ranks.gather_objects(mine)
        if t.ranks.main:
            torch.save({"params": {k: v.clone() for k, v in t.model.state_dict().items()}, "batches": got,
                        "grads": averaged_gradients(t)}, os.path.join(out, "seen.pt"))
    elif what == "die":
        t = Trainer(config(data, out, steps=50, checkpoint_every=1))
        t.sampler = Recorder(t.sampler, die_at=4 if t.ranks.rank == 1 else None)
        t.run()
    print(json.dumps({"rank": int(os.environ.get("RANK", 0)), "done": what}))


if __name__ == "__main__":
    from gnwarp.distributed import close
    done = False
    try:
        main(*sys.argv[1:4])
        done = True
    finally:
        close(sync=done)   # leave the process group before exit (else gloo may abort the process at exit)
