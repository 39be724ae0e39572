"""The DeepMind Control Suite domains: their own MJCF and assets, and DMC's control timesteps.

Each domain's model comes from dm_control (``dm_control.suite.<domain>.get_model_and_assets()``,
the optional extra ``pip install -e ".[dmc]"``); ``gnwarp.sim.systems.make("dmc-<domain>")`` loads
it through the MJCF checks into a ``System`` that steps at DMC's control timestep (``dt``) with
``substeps`` physics steps of the domain's own timestep.

    >>> domain("dmc-walker")            # Domain("dmc-walker", "walker", (), control_dt=0.025, ...)
    >>> xml, assets = model_source("dmc-walker")
"""
from __future__ import annotations

import dataclasses
import importlib

__all__ = ["Domain", "DOMAINS", "PREFIX", "domain", "is_dmc", "dmc_names", "model_source", "require_dm_control",
           "INSTALL_HINT"]

PREFIX = "dmc-"
INSTALL_HINT = 'pip install -e ".[dmc]"'


@dataclasses.dataclass(frozen=True)
class Domain:
    """One DMC domain as gnwarp loads it.

    ``module``: the suite module (``dm_control.suite.<module>``); ``args``: what its
    ``get_model_and_assets`` takes (the swimmer's number of bodies); ``control_dt``: DMC's control
    timestep in seconds (the suite module's ``_CONTROL_TIMESTEP``, else the model's timestep);
    ``physics_dt``: the model's own timestep; ``time_limit``: DMC's episode length in seconds;
    ``translation_axes``: the position axes (0: x, 1: y) along which the dynamics and rewards do
    not depend on position (empty: none)."""
    name: str
    module: str
    args: tuple
    control_dt: float
    physics_dt: float
    time_limit: float
    translation_axes: tuple

    @property
    def translation_invariant(self) -> bool:
        """Whether the dynamics are independent of the horizontal position along some axis."""
        return bool(self.translation_axes)

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return int(round(self.control_dt / self.physics_dt))

    @property
    def episode_steps(self) -> int:
        """Control steps of one DMC episode (time limit / control timestep)."""
        return int(round(self.time_limit / self.control_dt))


DOMAINS: dict[str, Domain] = {d.name: d for d in (
    Domain("dmc-cheetah", "cheetah", (), 0.01, 0.01, 10.0, (0,)),
    Domain("dmc-walker", "walker", (), 0.025, 0.0025, 25.0, (0,)),
    Domain("dmc-hopper", "hopper", (), 0.02, 0.005, 20.0, (0,)),
    Domain("dmc-swimmer6", "swimmer", (6,), 0.03, 0.002, 30.0, (0, 1)),
    Domain("dmc-reacher", "reacher", (), 0.02, 0.02, 20.0, ()),
    Domain("dmc-cartpole", "cartpole", (), 0.01, 0.01, 10.0, ()),
    Domain("dmc-pendulum", "pendulum", (), 0.02, 0.02, 20.0, ()),
    Domain("dmc-acrobot", "acrobot", (), 0.01, 0.01, 10.0, ()),
)}


def dmc_names() -> list[str]:
    """The DMC systems: "dmc-cheetah", "dmc-walker", ..."""
    return list(DOMAINS)


def is_dmc(name) -> bool:
    """Whether ``name`` is a DMC system name (its prefix "dmc-")."""
    return isinstance(name, str) and name.strip().lower().startswith(PREFIX)


def domain(name: str) -> Domain:
    """The ``Domain`` of a DMC system name; ValueError names the known ones."""
    d = DOMAINS.get(name.strip().lower()) if isinstance(name, str) else None
    if d is None:
        raise ValueError(f"unknown DMC system {name!r}; DMC systems: {', '.join(DOMAINS)}")
    return d


def require_dm_control(what: str = "the DeepMind Control Suite domains"):
    """``dm_control.suite``, imported on first use; ImportError naming the extra when missing."""
    try:
        import warnings
        with warnings.catch_warnings():  # dm_control asks for a display it does not need here
            warnings.simplefilter("ignore")
            return importlib.import_module("dm_control.suite")
    except ImportError as err:
        raise ImportError(f"{what} need the dm-control package: {INSTALL_HINT} "
                          f"(or pip install dm-control)") from err


def model_source(name: str) -> tuple[str, dict]:
    """(MJCF text, assets {file name: bytes}) of a DMC system, from its suite module's
    ``get_model_and_assets``."""
    d = domain(name)
    require_dm_control()
    module = importlib.import_module(f"dm_control.suite.{d.module}")
    xml, assets = module.get_model_and_assets(*d.args)
    if isinstance(xml, bytes):
        xml = xml.decode("utf-8")
    return xml, dict(assets)
