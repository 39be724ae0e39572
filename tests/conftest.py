"""Shared test settings."""
import pytest
import torch

from gnwarp.interop import warp

warp()  # initialize Warp once, quietly


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    # tiny GEMMs: one thread is as fast, and does not thrash when the 2-core machine is shared
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
