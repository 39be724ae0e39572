"""Shared test settings and fixtures."""
import importlib
import warnings

import mujoco
import pytest
import torch

from gnwarp.interop import warp

warp()  # initialize Warp once, quietly


@pytest.fixture(scope="module")
def suite_physics():
    """dm_control's suite Physics on this MuJoCo (needs dm_control: the DMC tests importorskip it):
    its index tables lose the fields MuJoCo no longer has (flex_vertedge, ...), restored afterwards.
    ``make(system)`` -> (the suite's task module, its Physics of the DMC system)."""
    from dm_control.mujoco.wrapper.mjbindings import sizes
    m = mujoco.MjModel.from_xml_string("<mujoco/>")
    d = mujoco.MjData(m)
    gone = {}
    for struct, obj in (("mjmodel", m), ("mjdata", d)):
        for field in list(sizes.array_sizes[struct]):
            if not hasattr(obj, field):
                gone[struct, field] = sizes.array_sizes[struct].pop(field)

    def make(system):
        from gnwarp.sim import dmc
        d = dmc.domain(system)
        module = importlib.import_module(f"dm_control.suite.{d.module}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return module, module.Physics.from_xml_string(*module.get_model_and_assets(*d.args))
    yield make
    for (struct, field), v in gone.items():
        sizes.array_sizes[struct][field] = v


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
