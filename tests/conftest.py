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


def pytest_configure(config):
    config.addinivalue_line("markers", "cuda: needs a CUDA GPU (the CUDA suite: pytest -m cuda tests)")


def pytest_collection_modifyitems(config, items):
    # every test skipped here for want of CUDA is in the CUDA suite, so `-m cuda` selects exactly it
    for item in items:
        if any(m.kwargs.get("reason") == "needs CUDA" for m in item.iter_markers("skipif")):
            item.add_marker(pytest.mark.cuda)
