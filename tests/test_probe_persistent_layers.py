"""bench/probes/persistent_layers.py on the CPU: the persistent chain's arithmetic (one thread,
the grid barrier compiled out) against float64, and its refusals. The barrier itself runs only on
a GPU (the probe checks its result there the same way)."""
import pytest
import torch

from bench.probes import persistent_layers as pl


def test_chain_of_layers_matches_float64_and_uneven_k_splits():
    w, b, x = pl._inputs(5, 12, 3, torch.device("cpu"), seed=1)
    for splits in (1, 5):   # 12 columns in chunks of 3 (the last split empty) and one chunk of 12
        chain = pl.Chain(w, b, x, blocks=1, splits=splits)
        assert pl.check(chain) < 1e-6
        assert pl.check(chain) < 1e-6   # a second call on the same buffers: zeroed again, the same chain
    chain.w[2, 0, 0] += 1.0   # the kernel reads the weights it is given
    out = chain.output().clone()
    chain()
    assert not torch.allclose(chain.output(), out)


def test_chain_refuses_several_cpu_blocks_and_mismatched_shapes():
    w, b, x = pl._inputs(2, 8, 1, torch.device("cpu"), seed=0)
    with pytest.raises(ValueError, match="one thread"):
        pl.Chain(w, b, x, blocks=2, splits=1)
    with pytest.raises(ValueError, match="square layers"):
        pl.Chain(w[:, :, :4], b, x, blocks=1, splits=1)
    with pytest.raises(ValueError, match="layers=3: 0 to 2"):
        pl.Chain(w, b, x, blocks=1, splits=1, layers=3)
    empty = pl.Chain(w, b, x, blocks=1, splits=1, layers=0)   # the launch alone: nothing added
    empty.sums.fill_(5.0)
    empty()
    assert float(empty.sums[0].abs().sum()) == 0.0 and float(empty.sums[1].min()) == 5.0


def test_splits_fill_the_blocks_and_stay_at_least_eight_wide():
    assert pl.splits_for(1, 256, 132) == 32            # 132 x 256 threads, 256 outputs: capped at 256 / 8
    assert pl.splits_for(16, 256, 8) == 1 and pl.splits_for(1, 256, 8) == 8
