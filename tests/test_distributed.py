"""Several ranks on the CPU (gloo), started as torchrun starts them: a training step over two
ranks against one process on the joint batch, resuming with another number of ranks, a rank that
dies, sharded generation against one process, and the ranks' helpers."""
from pathlib import Path

import numpy as np
import pytest
import torch

from gnwarp.data.format import ARRAYS, DatasetError
from gnwarp.data.generation import generate
from gnwarp.distributed import DistributedError, Ranks, collective, shard, timeout_seconds
from gnwarp.graphs import GraphsTuple, batch
from ranks import start_ranks

HERE = Path(__file__).parent
SMALL = dict(num_sequences=(6, 2, 2), num_steps=8, seed=5, backend="mujoco", progress=False)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("dist") / "cartpole.h5"
    generate("cartpole", **SMALL).save(path)
    return str(path)


@pytest.mark.parametrize("opt", ["adam", "flat_adam"])
def test_two_ranks_take_the_step_of_one_process_on_the_joint_batch_and_resume_on_one(data, tmp_path, opt):
    """torch's Adam: one all-reduce of the packed gradients; FlatAdam with ``overlap_allreduce``:
    GN2's span reduced during the backward (``GradientBuckets``), the rest after it."""
    from dist_worker import config
    from gnwarp.train.trainer import Trainer
    out = tmp_path / "two"
    codes, outs = start_ranks([str(HERE / "dist_worker.py"), "train", data, str(out)],
                              env={"OPT": opt, "OVERLAP": "1"})
    assert codes == [0, 0], "\n".join(outs)
    seen = torch.load(out / "seen.pt", weights_only=True)
    parts = sorted(seen["batches"], key=lambda b: b["rank"])
    assert len(parts) == 2
    assert [p["early_buckets"] for p in parts] == ([None, None] if opt == "adam" else [1, 1])
    g0, g1 = (GraphsTuple(**p["graph"]) for p in parts)
    assert not torch.equal(g0.nodes, g1.nodes), "the ranks drew the same batch"
    joint = (batch([g0, g1]), torch.cat([p["target"] for p in parts]))

    class Joint:
        static_shapes = True

        def sample(self, n, gen):
            assert n == 8
            return joint

    one = Trainer(config(data, str(tmp_path / "one"), batch_size=8, optimizer=opt))
    one.sampler = Joint()
    one.run()
    # the averaged gradients themselves (Adam's first step hides a gradient's scale), then the weights
    from dist_worker import averaged_gradients
    torch.testing.assert_close(seen["grads"], averaged_gradients(one), rtol=1e-5, atol=1e-7)
    mine = one.model.state_dict()
    assert set(mine) == set(seen["params"])
    for k, v in seen["params"].items():
        torch.testing.assert_close(v, mine[k], rtol=1e-5, atol=1e-6, msg=lambda m: f"{k}: {m}")
    moved = [k for k, v in seen["params"].items() if v.is_floating_point() and "norm" not in k]
    init = Trainer(config(data, str(tmp_path / "init"), steps=0)).model.state_dict()
    assert any(not torch.equal(init[k], seen["params"][k]) for k in moved), "the step changed no weight"
    # the two-rank run resumes in one process (another number of ranks) and goes on from its step
    r = Trainer(config(data, str(out), steps=3, optimizer=opt)).run()
    assert r["steps"] == 3
    rows = (out / "log.csv").read_text().splitlines()
    assert [row.split(",")[0] for row in rows[1:]] == ["1", "2", "3"]


def test_a_rank_that_dies_ends_the_others_with_a_clear_error_and_leaves_intact_checkpoints(data, tmp_path):
    from gnwarp.train import load_model
    out = tmp_path / "die"
    # the survivor must end by itself: a hang past `wait` fails the test
    codes, outs = start_ranks([str(HERE / "dist_worker.py"), "die", data, str(out)], timeout=20, wait=120)
    assert codes[1] == 3
    assert codes[0] != 0, outs[0]
    assert "DistributedError" in outs[0] and "rank 0 of 2" in outs[0], outs[0]
    model = load_model(out / "last")          # the checkpoint rank 0 wrote last is whole
    assert sum(p.numel() for p in model.parameters()) > 0
    assert not [p for p in out.rglob("*") if ".tmp" in p.name or "partial" in p.name]


def test_sharded_generation_over_two_ranks_is_the_one_process_dataset(tmp_path):
    out = tmp_path / "sharded.h5"
    args = ["-m", "gnwarp.cli", "generate", "cartpole", "--train", "6", "--valid", "2", "--test", "2", "--steps", "8",
            "--seed", "5", "--backend", "mujoco", "-q", "-o", str(out)]
    codes, outs = start_ranks(args)
    assert codes == [0, 0], "\n".join(outs)
    assert "rank 1 of 2: 5 sequences" in "\n".join(outs)
    assert not list(tmp_path.glob("*.shard-*")), "the shards were not removed"
    from gnwarp.data.dataset import load
    one, two = generate("cartpole", **SMALL), load(out, lazy=False)
    for k in one.splits:
        for a in ARRAYS:
            x, y = np.asarray(getattr(one[k], a)), np.asarray(getattr(two[k], a))
            assert x.dtype == y.dtype and np.array_equal(x, y), (k, a)
    assert two.meta["ranks"] == 2


def test_shards_merge_back_in_place_and_refuse_what_is_not_one_generation():
    from gnwarp.data.shards import merge
    kw = dict(SMALL, num_sequences=(4, 1, 2))
    one = generate("cartpole", **kw)
    shards = [generate("cartpole", shard=(r, 3), **kw) for r in (2, 0, 1)]
    assert [len(s["train"]) for s in shards] == [1, 2, 1]
    m = merge(shards)
    for k in one.splits:
        assert np.array_equal(np.asarray(one[k].body), m[k].body), k
    with pytest.raises(DatasetError, match="needs each of 0..2 once"):
        merge(shards[:2])
    with pytest.raises(DatasetError, match="differs in seed"):
        merge([shards[0], generate("cartpole", shard=(0, 3), **dict(kw, seed=6)), shards[2]])
    with pytest.raises(DatasetError, match="not a shard"):
        merge([one])
    with pytest.raises(ValueError, match="0 <= rank < ranks"):
        generate("cartpole", shard=(3, 3), **kw)


def test_ranks_helpers_for_a_single_process(monkeypatch):
    assert list(shard(7, 1, 3)) == [1, 4]
    assert sorted(i for r in range(3) for i in shard(7, r, 3)) == list(range(7))
    with pytest.raises(ValueError, match="rank 3"):
        shard(5, 3, 3)
    one = Ranks()
    t = torch.ones(3)
    assert one.all_reduce_(t, mean=True) is t and t.tolist() == [1, 1, 1]
    assert one.gather_objects({"a": 1}) == [{"a": 1}] and one.broadcast_object(5) == 5 and one.main
    assert one.on_main("a value", lambda: 7) == 7
    monkeypatch.setenv("GNWARP_DIST_TIMEOUT", "0")
    with pytest.raises(ValueError, match="GNWARP_DIST_TIMEOUT"):
        timeout_seconds()
    monkeypatch.setenv("GNWARP_DIST_TIMEOUT", "30")
    with pytest.raises(DistributedError, match="rank 1 of 2: all_reduce"):
        with collective(Ranks(rank=1, world=2), "all_reduce"):
            raise RuntimeError("Connection closed by peer")


def test_normalizers_summed_together_match_each_normalizer_alone():
    from gnwarp.models.normalizer import Normalizer, accumulate_over_ranks
    g = torch.Generator().manual_seed(0)
    alone = [Normalizer(3), Normalizer(5)]
    together = [Normalizer(3), Normalizer(5)]
    for _ in range(2):   # twice: the second batch adds to sums already there
        x, y = torch.randn(7, 3, generator=g) * 3 + 1, torch.randn(4, 5, generator=g, dtype=torch.float64)
        w = (torch.rand(4, generator=g) > 0.3).to(torch.float64)
        want = [alone[0].accumulate_stats(x), alone[1].accumulate_stats(y, w)]
        got = accumulate_over_ranks([(together[0], x, None), (together[1], y, w)], Ranks())
        for (m0, s0), (m1, s1) in zip(want, got):
            assert m1.dtype == m0.dtype
            torch.testing.assert_close(m1, m0)
            torch.testing.assert_close(s1, s0)
    for a, b in zip(alone, together):
        assert a.count.item() == b.count.item() and torch.allclose(a.sumsq, b.sumsq)
    with pytest.raises(ValueError, match="listed twice"):
        accumulate_over_ranks([(alone[0], x, None), (alone[0], x, None)], Ranks())
    half = torch.randn(5, 3, generator=g).to(torch.float16)   # statistics in the input's dtype, as alone
    (m1, s1), = accumulate_over_ranks([(Normalizer(3), half, None)], Ranks())
    m0, s0 = Normalizer(3).accumulate_stats(half)
    assert m1.dtype == s1.dtype == m0.dtype == torch.float16
    torch.testing.assert_close(m1, m0)
    torch.testing.assert_close(s1, s0)


class _PairedRank:
    """Rank ``rank`` of two whose all-reduce adds the pack the other rank made (``other``), and
    keeps its own (``packed``): two ranks' collective played in one process."""

    def __init__(self, rank, other=None):
        self.rank, self.other, self.packed = rank, other, None

    def all_reduce_(self, t):
        self.packed = t.clone()
        if self.other is not None:
            t.add_(self.other)
        return t


def test_over_two_ranks_the_normalizers_take_both_batches_on_top_of_rank_0_totals():
    from gnwarp.models.normalizer import Normalizer, accumulate_over_ranks
    g = torch.Generator().manual_seed(1)
    one, r0, r1 = ([Normalizer(3), Normalizer(2, std_floor=0.5)] for _ in range(3))
    for k in range(2):   # what every rank already holds: rank 0's totals, the same on rank 1
        x = torch.randn(5, (3, 2)[k], generator=g)
        one[k].accumulate(x), r0[k].accumulate(x), r1[k].accumulate(x)
    xs = [torch.randn(6, 3, generator=g) * 2, torch.randn(4, 3, generator=g) - 1]   # rank 0's, rank 1's
    ys = [torch.randn(3, 2, generator=g), torch.randn(5, 2, generator=g)]
    ws = [torch.tensor([1.0, 0.0, 1.0]), torch.ones(5)]
    second = _PairedRank(1)
    accumulate_over_ranks([(r1[0], xs[1], None), (r1[1], ys[1], ws[1])], second)
    got = accumulate_over_ranks([(r0[0], xs[0], None), (r0[1], ys[0], ws[0])], _PairedRank(0, second.packed))
    want = [one[0].accumulate_stats(torch.cat(xs)), one[1].accumulate_stats(torch.cat(ys), torch.cat(ws))]
    assert second.packed[0].item() == 4 and second.packed[1 + 3 + 3].item() == 5, "rank 1 packs its batch alone"
    for (m0, s0), (m1, s1) in zip(want, got):
        torch.testing.assert_close(m1, m0)
        torch.testing.assert_close(s1, s0)
    for a, b in zip(one, r0):
        assert a.count.item() == b.count.item() == 5 + (10 if a.size == 3 else 7)
        torch.testing.assert_close(b.sum, a.sum)
        torch.testing.assert_close(b.sumsq, a.sumsq)


class _Recording:
    """A rank of two that records what it is asked to all-reduce (no other process): the range of
    the flat gradient, whether asynchronous, the sum of |gradient| before it, and a copy of it."""
    distributed, world, rank = True, 2, 0

    def __init__(self, flat):
        self.flat, self.calls = flat, []

    def all_reduce_(self, t, mean=False, async_op=False):
        start = (t.data_ptr() - self.flat.data_ptr()) // t.element_size()
        self.calls.append((start, start + t.numel(), async_op, float(self.flat[:start].abs().sum()), t.clone()))
        return _Done(t) if async_op else t


class _Done:
    def __init__(self, t):
        self.t = t

    def wait(self):
        return self.t


def test_gn2_gradients_go_out_complete_during_the_backward_before_gn1_has_any(data, tmp_path):
    from dist_worker import config
    from gnwarp.train.overlap import GradientBuckets
    from gnwarp.train.trainer import Trainer
    t = Trainer(config(data, str(tmp_path / "o"), optimizer="flat_adam"))
    flat = t.optimizer.grad_flat
    fake = _Recording(flat)
    buckets = GradientBuckets.for_model(fake, t.optimizer, t.model)
    gn2 = list(t.model.core.gn2.parameters())
    offsets = dict(zip(map(id, t.optimizer.param_groups[0]["params"]), t.optimizer.offsets))
    # GN2's span, with the padding after its last parameter (it ends the buffer): two reductions a step
    assert (buckets.start, buckets.end) == (offsets[id(gn2[0])], flat.numel()) and buckets.rest == [(0, buckets.start)]
    g, target = t.sample()
    for calls in (1, 2):   # the model once, then twice in one step: sent after the last call's GN2 backward
        sent = buckets.sent
        with buckets.armed():
            loss = sum(t.loss(g, target)["loss"] for _ in range(calls))
        t.optimizer.zero_grad()
        loss.backward()
        assert buckets.calls == buckets.signals == calls and buckets.sent == sent + 1, "one early bucket a step"
        assert len(fake.calls) == 1 and fake.calls[0][:3] == (buckets.start, buckets.end, True)
        if calls == 1:
            assert fake.calls[0][3] == 0.0, "GN1's gradients had begun when GN2's went out"
        assert torch.equal(fake.calls[0][4], flat[buckets.start:buckets.end]), "GN2's span was sent incomplete"
        assert flat[buckets.start:buckets.end].abs().sum() > 0 and flat[:buckets.start].abs().sum() > 0
        buckets.reduce()
        assert [c[:3] for c in fake.calls[1:]] == [(0, buckets.start, False)] and buckets.pending is None
        fake.calls.clear()
    # a GN2 gradient outside the flat buffer at the signal: the whole buffer after the backward
    with buckets.armed():
        terms = t.loss(g, target)
    t.optimizer.zero_grad()
    p = gn2[0]
    p.grad = torch.zeros_like(p)
    terms["loss"].backward()
    assert fake.calls == [] and buckets.skipped
    buckets.reduce()
    assert [c[:3] for c in fake.calls] == [(0, flat.numel(), False)] and p.grad is None
    # one that arrives after its bucket went out: an error, not a gradient averaged in part
    fake.calls.clear()
    with buckets.armed():
        terms = t.loss(g, target)
    t.optimizer.zero_grad()
    terms["loss"].backward()
    p.grad = torch.ones_like(p)
    with pytest.raises(RuntimeError, match="arrived in p.grad after its bucket"):
        buckets.reduce()
    assert buckets.pending is None, "the early reduction was left under way"
    assert GradientBuckets.for_model(Ranks(), t.optimizer, t.model) is None
    done = Ranks().all_reduce_(torch.ones(2), mean=True, async_op=True)
    assert done.wait().tolist() == [1.0, 1.0]


@pytest.mark.parametrize("backend", ["nccl", "gloo"])
def test_close_leaves_an_nccl_group_to_the_exit_and_destroys_a_gloo_one(backend, monkeypatch):
    """``close()``: on NCCL only the gloo side group is destroyed (destroying the NCCL group hangs
    after captured NCCL collectives, pytorch#115388); on gloo the whole group is; both forget the ranks."""
    import torch.distributed as dist

    import gnwarp.distributed as gd
    destroyed = []
    side = object()
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist, "get_backend", lambda group=None: backend)
    monkeypatch.setattr(dist, "destroy_process_group", lambda group=None: destroyed.append(group))
    monkeypatch.setattr(gd, "_RANKS", Ranks(rank=0, world=2, device=torch.device("cpu"), backend=backend))
    monkeypatch.setattr(gd, "_OBJECTS", side if backend == "nccl" else None)
    gd.close()
    assert destroyed == ([side] if backend == "nccl" else [None])
    assert gd._RANKS is None and gd._OBJECTS is None
    if backend == "nccl":   # the NCCL group lives on: a later CPU request is refused, not put on top of it
        monkeypatch.setenv("WORLD_SIZE", "2")
        monkeypatch.setenv("RANK", "0")
        monkeypatch.setattr(gd, "launched", lambda: True)
        with pytest.raises(ValueError, match="runs on cuda"):
            gd.ranks("cpu")
