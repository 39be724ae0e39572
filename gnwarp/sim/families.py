"""One record per built-in system family: builder, timesteps, parameter ranges, the element each
parameter describes, the initial-state spec and the parsing of names such as "swimmer6".

    >>> fam, n = parse_name("swimmer6")          # (FAMILIES["swimmer"], 6)
    >>> family_of("my_robot")                    # None: not a built-in name
    >>> family_name("swimmer6"), family_name("my_robot")   # ("swimmer", "my_robot")
    >>> fam.ranges(n)                            # [(parameter, group label, (lo, hi)), ...]
"""
from __future__ import annotations

import dataclasses
import re
from typing import Callable

import mujoco

from gnwarp.sim.builders import (CHEETAH_BODIES, CHEETAH_LIMBS, JACO_ACTUATOR_NAMES, JACO_BODIES, build_acrobot,
                                 build_cartpole, build_cheetah, build_jaco, build_pendulum, build_swimmer,
                                 build_walker)

__all__ = ["Family", "FAMILIES", "parse_name", "family_of", "family_name"]

Range = tuple[str, str, tuple[float, float]]


@dataclasses.dataclass(frozen=True)
class Family:
    """A built-in system family.

    ``build(params, timestep) -> MjSpec``; ``dt``: data timestep (s); ``substeps``: physics steps
    per data step; ``translation_axes``: the position axes (0: x, 1: y) along which the dynamics
    and rewards do not depend on position (empty: none; ``translation_invariant`` says whether any);
    ``full_circle``: random initial states draw unlimited hinges over the full circle (else
    +-0.1 rad around the reference pose); ``links``: the sizes "<name><N>" may take (None: the
    name takes no size), ``sampled_links``: the sizes its parameterized variant samples,
    ``default_links``: the size of the fixed system.
    """

    name: str
    build: Callable[[dict[str, float], float], mujoco.MjSpec]
    dt: float
    substeps: int
    translation_axes: tuple[int, ...]
    full_circle: bool
    links: tuple[int, int] | None = None
    sampled_links: tuple[int, int] | None = None
    default_links: int | None = None

    @property
    def translation_invariant(self) -> bool:
        """Whether the dynamics are independent of the horizontal position along some axis."""
        return bool(self.translation_axes)

    def ranges(self, n: int | None = None) -> list[Range]:
        """(parameter, group label, range) of every parameter, in sampling order ([] for a
        family without a parameterized variant); ``n``: the size a name fixes (None: sampled)."""
        return _ranges(self.name, n, self)

    def element(self, key: str) -> tuple[int, str] | None:
        """The element a parameter describes: (mujoco.mjtObj body or actuator, its name), or None
        for a parameter of the whole system (the swimmer's number of links)."""
        return _element(self.name, key)

    def defaults(self, n: int | None = None) -> dict[str, float]:
        """The parameters of the fixed system (of size ``n`` where the family has sizes)."""
        out = {}
        for key, _, _ in self.ranges(n):
            if key == "n_links":
                out[key] = float(n if n is not None else self.default_links)
            elif key.startswith("base_angle_"):
                out[key] = 0.0
            else:
                out[key] = 1.0
        if self.links is not None:  # only the links that exist
            links = int(out["n_links"])
            out = {k: v for k, v in out.items()
                   if not k.startswith("link_") or int(k.rsplit("_", 1)[1]) < links}
        return out


def _ranges(family: str, n: int | None, fam: Family) -> list[Range]:
    if family == "pendulum":
        return [("length", "length", (0.2, 1.0)), ("mass", "mass", (0.5, 3.0))]
    if family == "cartpole":
        return [("cart_mass", "cart_mass", (0.2, 2.0)),
                ("pole_length", "pole_length", (0.3, 1.0)),
                ("pole_thickness", "pole_thickness", (0.4, 2.2))]
    if family == "swimmer":
        # Without a suffix the number of links is a parameter; with one it is fixed.
        links = (float(n), float(n)) if n is not None else tuple(map(float, fam.sampled_links))
        out = [("n_links", "n_links", links)]
        for i in range(int(links[1])):
            out.append((f"link_length_{i}", "link_length_*", (0.3, 2.0)))
            out.append((f"link_thickness_{i}", "link_thickness_*", (0.5, 5.0)))
        return out
    if family == "cheetah":
        out = [(f"base_angle_{b}", "base_angle_*", (-0.1, 0.1)) for b in CHEETAH_LIMBS]
        out += [(f"length_{b}", "length_*", (0.5, 2.0)) for b in CHEETAH_BODIES]
        out += [(f"thickness_{b}", "thickness_*", (0.5, 2.0)) for b in CHEETAH_BODIES]
        return out
    if family == "jaco":
        return ([(f"mass_{b}", "mass_*", (0.5, 1.5)) for b in JACO_BODIES]
                + [(f"gear_{a}", "gear_*", (0.5, 1.5)) for a in JACO_ACTUATOR_NAMES])
    return []  # acrobot, walker: no parameterized variant in the paper


def _element(family: str, key: str) -> tuple[int, str] | None:
    body, act = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_ACTUATOR
    if family == "pendulum":
        return body, "pole"
    if family == "cartpole":
        return body, "cart" if key == "cart_mass" else "pole_1"
    if family == "swimmer":
        if key == "n_links":
            return None
        i = int(key.rsplit("_", 1)[1])
        return body, "head" if i == 0 else f"segment_{i - 1}"
    if family == "cheetah":
        return body, key.split("_", 1)[1].removeprefix("angle_")
    if family == "jaco":
        kind, name = key.split("_", 1)
        return (act if kind == "gear" else body), name
    return None


def _build_cheetah(p: dict[str, float], timestep: float) -> mujoco.MjSpec:
    # the cheetah's density and clearance are calibrated on the fixed system, whose parameters live here
    return build_cheetah(p, timestep, FAMILIES["cheetah"].defaults())


FAMILIES: dict[str, Family] = {
    "pendulum": Family("pendulum", build_pendulum, dt=0.02, substeps=1, translation_axes=(),
                       full_circle=True),
    "cartpole": Family("cartpole", build_cartpole, dt=0.01, substeps=1, translation_axes=(),
                       full_circle=True),
    "acrobot": Family("acrobot", build_acrobot, dt=0.01, substeps=1, translation_axes=(), full_circle=True),
    # dm_control's swimmer steps at 2 ms; SwimmerN exists for N in 3..15, the parameterized one samples 3..9 (paper B)
    "swimmer": Family("swimmer", build_swimmer, dt=0.02, substeps=10, translation_axes=(0, 1), full_circle=False,
                      links=(3, 15), sampled_links=(3, 9), default_links=6),
    "cheetah": Family("cheetah", _build_cheetah, dt=0.01, substeps=1, translation_axes=(0,), full_circle=False),
    "walker": Family("walker", build_walker, dt=0.0025, substeps=1, translation_axes=(0,), full_circle=False),
    # 100 ms data steps over 10 ms implicit physics steps.
    "jaco": Family("jaco", build_jaco, dt=0.1, substeps=10, translation_axes=(), full_circle=False),
}


def _sized() -> str:
    return ", ".join(f"{f.name} takes a number of links {f.links[0]}..{f.links[1]} as a suffix, e.g. "
                     f"{f.name}{f.default_links}" for f in FAMILIES.values() if f.links is not None)


def parse_name(name: str) -> tuple[Family, int | None]:
    """The family of a built-in system name and the size the name fixes ("swimmer6" ->
    (swimmer, 6); "swimmer" -> (swimmer, None)). Raises ValueError for any other name."""
    if not isinstance(name, str):
        raise ValueError(f"system name must be a string, got {name!r}")
    key = name.strip().lower()
    if key in FAMILIES:
        return FAMILIES[key], None
    match = re.fullmatch(r"([a-z_]+?)(\d+)", key)
    fam = FAMILIES.get(match.group(1)) if match else None
    if fam is not None and fam.links is not None:
        n = int(match.group(2))
        lo, hi = fam.links
        if not lo <= n <= hi:
            raise ValueError(f"{fam.name}{n}: the {fam.name} has {lo} to {hi} links, got {n}")
        return fam, n
    raise ValueError(f"unknown system {name!r}; valid systems: {', '.join(FAMILIES)} ({_sized()})")


def family_of(name: str) -> Family | None:
    """The family of a built-in system name ("swimmer6" -> swimmer), None for any other name (a
    user MJCF file's stem)."""
    try:
        return parse_name(name)[0]
    except ValueError:
        return None


def family_name(name: str) -> str:
    """A system name without its size: "swimmer6" -> "swimmer"; a name that is not built-in (a
    user MJCF file's stem) is its own family."""
    fam = family_of(name)
    return fam.name if fam is not None else name
