"""The paper's seven MuJoCo systems (supplementary section B) and user MJCF files: the registry.

Every system is built with `mujoco.MjSpec` (by ``gnwarp.sim.builders``), mirroring the DeepMind
Control Suite models (suite/pendulum.xml, cartpole.xml, acrobot.xml, swimmer.py, cheetah.xml,
walker.xml) and the Kinova JACO of dm_control's manipulation suite (third_party/kinova, with
capsules in place of the meshes). A `System` is a compiled `mujoco.MjModel` plus the data
timestep at which datasets record states; the physics steps `substeps` times per data step.

Parameterized variants draw relative factors uniformly in the paper's ranges (section B, last
column). Where a size changes, geoms carry a density rather than a mass, so masses and inertias
follow the sizes; child bodies move with the length of their parent so the chain stays connected.

    >>> pendulum = make("pendulum")                       # fixed
    >>> pendulum = make("pendulum", seed=3)               # factors sampled with default_rng(3)
    >>> pendulum = make("pendulum", params={"length": 0.5})   # exactly these factors
    >>> custom = from_mjcf("my_robot.xml", dt=0.02, substeps=4)
    >>> cheetah = make("dmc-cheetah")   # DMC's own MJCF (gnwarp.sim.dmc; the [dmc] extra)
"""
from __future__ import annotations

import dataclasses
import math
import numbers
import pathlib
import warnings

import mujoco
import numpy as np

from gnwarp.sim.actuators import Actuators
from gnwarp.sim.families import FAMILIES, family_of, parse_name

__all__ = [
    "System",
    "names",
    "translation_axes",
    "make",
    "param_ranges",
    "param_places",
    "sample_params",
    "from_mjcf",
    "from_mjcf_string",
    "check_model",
    "describe",
    "MASS_RANGE",
    "SIZE_RANGE",
    "INERTIA_MAX",
]

# What the pipeline accepts of a model (``check_model``): masses of moving bodies in kg, geom sizes in
# m (planes may be 0: infinite), principal inertias in kg m^2 (up to MASS_RANGE[1] x 1e3 m squared),
# every other listed field finite; welded (jointless) bodies may be massless.
MASS_RANGE = (1e-6, 1e6)
SIZE_RANGE = (1e-6, 1e6)
INERTIA_MAX = 1e12
_CTRL_MAX = 1e6  # |actuator ctrl range|: datasets store controls within +-1e6 (gnwarp.data.checks.MAX_ABS)



@dataclasses.dataclass(eq=False)
class System:
    """A compiled MuJoCo model and the timesteps at which it is simulated and recorded.

    Attributes:
      name: "pendulum", "cartpole", "acrobot", "swimmer<N>", "cheetah", "walker", "jaco", or the
        stem of a user MJCF file.
      model: the compiled model; `model.opt.timestep == dt / substeps`.
      dt: data timestep in seconds (the interval between recorded states).
      substeps: physics steps per data step.
      params: the parameter factors this instance was built with (empty for fixed systems).
      parameterized: whether this is an instance of a parameterized variant.
      translation_axes: the position axes (0: x, 1: y) along which the dynamics and rewards do
        not depend on position (swimmer: x and y, cheetah and walker: x; paper D.4 re-centers
        these before prediction); ``translation_invariant`` says whether there is any.
      source: "builtin", "dm_control" (a DMC domain, ``gnwarp.sim.dmc``), or the path of the MJCF
        file ("string" for MJCF text).
      spec: the `mujoco.MjSpec` the model was compiled from (to derive variants of the model,
        e.g. with sensors added, without re-parsing).
    """

    name: str
    model: mujoco.MjModel
    dt: float
    substeps: int
    params: dict[str, float] = dataclasses.field(default_factory=dict)
    parameterized: bool = False
    translation_axes: tuple[int, ...] = ()
    source: str = "builtin"
    spec: mujoco.MjSpec | None = dataclasses.field(default=None, repr=False)

    @property
    def translation_invariant(self) -> bool:
        """Whether the dynamics do not depend on the horizontal position along some axis."""
        return bool(self.translation_axes)

    @property
    def nbody(self) -> int:
        """Number of bodies, the world included (= graph nodes)."""
        return self.model.nbody

    @property
    def nq(self) -> int:
        return self.model.nq

    @property
    def nv(self) -> int:
        return self.model.nv

    @property
    def nu(self) -> int:
        return self.model.nu

    @property
    def njnt(self) -> int:
        return self.model.njnt

    @property
    def actuators(self) -> Actuators:
        """The actuators' record (control ranges, limits, clamping) of ``model`` as it is now."""
        return Actuators.from_model(self.model)

    @property
    def timestep(self) -> float:
        """Physics timestep in seconds (dt / substeps)."""
        return float(self.model.opt.timestep)

    @property
    def contacts(self) -> bool:
        """Whether the model computes contacts (neither contacts nor constraints disabled)."""
        off = mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        return not (int(self.model.opt.disableflags) & int(off))


# ------------------------------------------------------------------------------------------------
# The registry: one record per family (``gnwarp.sim.families``) and the instances built from it.


def names() -> list[str]:
    """The built-in systems. The swimmer takes its number of links as a suffix: "swimmer6"."""
    return list(FAMILIES)


def param_ranges(name: str) -> dict[str, tuple[float, float]]:
    """The range of every parameter of a system ({} for acrobot and walker).

    Factors are relative to the fixed system (1.0), except the cheetah's base angles (absolute,
    radians, fixed value 0) and the swimmer's integer "n_links" ("swimmer" samples it in 3..9;
    "swimmer<N>" fixes it to N). DMC systems ("dmc-cheetah", ...) have none ({}).
    """
    from gnwarp.sim import dmc
    if dmc.is_dmc(name):
        dmc.domain(name)   # an unknown DMC name raises
        return {}
    fam, n = parse_name(name)
    return {key: rng for key, _, rng in fam.ranges(n)}


def param_places(system: "System", names=None) -> list[tuple[str, int]]:
    """Where each parameter of a parameterized ``system`` lives in its graph: ("nodes", body id)
    for a body's (a length, thickness, mass or base angle), ("edges", actuator id) for an
    actuator's (a gear: the edges of its joint, both directions), ("globals", 0) for the whole
    system's (every parameter of a system that is not one of the registry's, e.g. a variant
    renamed by its maker). ``names``: the parameters, in order (default: ``system.params``'s)."""
    try:
        fam, _ = parse_name(system.name)
    except ValueError:
        fam = None
    names = list(system.params) if names is None else list(names)
    out = []
    for key in names:
        el = fam.element(key) if fam is not None else None
        if el is None:
            out.append(("globals", 0))
            continue
        i = mujoco.mj_name2id(system.model, el[0], el[1])
        if i < 0:
            raise ValueError(f"{system.name}: parameter {key!r} describes {el[1]!r}, which the model lacks")
        out.append(("nodes" if el[0] == mujoco.mjtObj.mjOBJ_BODY else "edges", int(i)))
    return out


def _no_variant(name: str) -> ValueError:
    with_variant = [f.name for f in FAMILIES.values() if f.ranges()]
    return ValueError(f"{name} has no parameterized variant (the paper varies only "
                      f"{', '.join(with_variant)}); use make({name!r}) for the fixed system")


def sample_params(name: str, rng: np.random.Generator) -> dict[str, float]:
    """Draws every parameter uniformly in its range (the swimmer's n_links uniformly in 3..9).

    Returns the full parameter dict of one instance, as stored in `System.params`.
    """
    from gnwarp.sim import dmc
    if dmc.is_dmc(name):
        raise ValueError(f"{dmc.domain(name).name} has no parameterized variant (DMC's domains are fixed)")
    fam, n = parse_name(name)
    ranges = fam.ranges(n)
    if not ranges:
        raise _no_variant(name)
    out: dict[str, float] = {}
    if fam.links is not None:
        lo, hi = (int(v) for v in ranges[0][2])
        links = int(rng.integers(lo, hi + 1))
        out["n_links"] = float(links)
        per_link = {key: rng_ for key, _, rng_ in ranges}   # every link shares link 0's ranges
        lengths = rng.uniform(*per_link["link_length_0"], size=links)
        thicknesses = rng.uniform(*per_link["link_thickness_0"], size=links)
        for i in range(links):
            out[f"link_length_{i}"] = float(lengths[i])
            out[f"link_thickness_{i}"] = float(thicknesses[i])
        return out
    for key, _, (lo, hi) in ranges:
        out[key] = float(rng.uniform(lo, hi))
    return out


def _validate(name: str, fam, n: int | None, params: dict) -> dict[str, float]:
    """Checks user parameters against their ranges; returns the full dict with defaults filled."""
    ranges = param_ranges(name)
    if not ranges:
        raise _no_variant(name)
    if not isinstance(params, dict):
        raise ValueError(f"{name}: params must be a dict of parameter name -> value, "
                         f"got {type(params).__name__}")
    unknown = sorted(set(params) - set(ranges))
    if unknown:
        raise ValueError(f"{name}: unknown parameter(s) {', '.join(map(repr, unknown))}; "
                         f"valid: {', '.join(ranges)}")
    checked: dict[str, float] = {}
    for key, value in params.items():
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"{name}: parameter {key!r} must be a number, got {value!r}")
        value = float(value)
        lo, hi = ranges[key]
        if not (math.isfinite(value) and lo <= value <= hi):
            hint = ""
            if key == "n_links" and n is not None:
                hint = " (make('swimmer', ...) varies the number of links)"
            raise ValueError(f"{name}: parameter {key!r}={value!r} is outside its range "
                             f"[{lo}, {hi}]{hint}")
        if key == "n_links" and value != int(value):
            raise ValueError(f"{name}: parameter 'n_links' must be an integer, got {value!r}")
        checked[key] = value
    links = int(checked.get("n_links", n if n is not None else fam.default_links or 0))
    full = fam.defaults(links if fam.links is not None else n)
    extra = sorted(k for k in checked if k not in full)
    if extra:
        raise ValueError(f"{name}: parameter(s) {', '.join(map(repr, extra))} name links beyond "
                         f"the swimmer's {links} links")
    full.update(checked)
    return full


def make(name: str, params: dict[str, float] | None = None, seed: int | None = None) -> System:
    """Builds a built-in system.

    Args:
      name: one of `names()`; the swimmer as "swimmer<N>" (N = 3..15), "swimmer" means swimmer6
        when fixed and samples N in 3..9 when parameterized; or a DMC system
        (``gnwarp.sim.dmc.dmc_names()``: "dmc-cheetah", ...; fixed only) whose ``dt`` is DMC's
        control timestep.
      params: exact parameters of a parameterized instance (see `param_ranges`); missing ones
        take the fixed system's value.
      seed: with params=None, samples the parameters with `np.random.default_rng(seed)`.

    Returns:
      the fixed system if neither params nor seed is given, else a parameterized instance whose
      full parameter dict is `System.params`.
    """
    from gnwarp.sim import dmc
    if dmc.is_dmc(name):
        return _make_dmc(name, params, seed)
    fam, n = parse_name(name)
    if params is not None and seed is not None:
        raise ValueError(f"{name}: give either params or seed, not both")
    if params is None and seed is None:
        full, parameterized = fam.defaults(n), False
    elif params is None:
        full, parameterized = sample_params(name, np.random.default_rng(seed)), True
    else:
        full, parameterized = _validate(name, fam, n, params), True
    spec = fam.build(full, fam.dt / fam.substeps)
    system_name = f"{fam.name}{int(full['n_links'])}" if fam.links is not None else fam.name
    model = spec.compile()
    check_model(model, system_name)
    return System(name=system_name, model=model, dt=fam.dt, substeps=fam.substeps,
                  params=full if parameterized else {}, parameterized=parameterized,
                  translation_axes=fam.translation_axes, spec=spec)


def _check_timing(where, dt, substeps) -> None:
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"{where}: substeps must be a positive integer, got {substeps!r}")
    if dt is not None and not (isinstance(dt, numbers.Real) and not isinstance(dt, bool)
                               and math.isfinite(dt) and dt > 0):
        raise ValueError(f"{where}: dt must be a positive number of seconds, got {dt!r}")


def _compile_checked(load, where: str, dt: float | None, substeps: int, numbers_check=None):
    """(spec, model, dt) of an MJCF model: ``load()`` gives its ``MjSpec``; the physics timestep
    becomes dt / substeps when ``dt`` is given; ``numbers_check()`` refuses NaN / Inf in the text
    before ``check_model`` and the joint and actuator checks run. ValueError names ``where``."""
    try:
        spec = load()
        if dt is not None:
            spec.option.timestep = float(dt) / int(substeps)
        with warnings.catch_warnings():  # a deprecated compiler attribute (DMC's settotalmass) still compiles
            warnings.filterwarnings("ignore", message="compiler attribute")
            model = spec.compile()
    except Exception as err:  # mujoco reports every parse and compile error as ValueError
        raise ValueError(f"{where}: not a valid MJCF model: {err}".rstrip()) from err
    if numbers_check is not None:
        numbers_check()  # MuJoCo reads "nan" as "not given" in places (geom mass): refuse it
    check_model(model, where)
    if model.njnt == 0:
        raise ValueError(f"{where}: the model has no joints; gnwarp needs at least one joint "
                         "(joints are the graph's edges)")
    if model.nu == 0:
        raise ValueError(f"{where}: the model has no actuators; gnwarp needs at least one "
                         "actuator (actions drive the dynamics)")
    if dt is None:
        dt = float(model.opt.timestep) * int(substeps)
    return spec, model, float(dt)


def from_mjcf(path, dt: float | None = None, substeps: int = 1) -> System:
    """Loads a user MJCF file as a fixed system.

    Args:
      path: the MJCF file (includes and assets resolve relative to it).
      dt: data timestep in seconds; default the file's timestep times `substeps`. When given, the
        physics timestep becomes dt / substeps.
      substeps: physics steps per data step (>= 1).

    Raises:
      FileNotFoundError: no such file.
      ValueError: the file does not compile, has no joints or no actuators, bad dt/substeps, a
        NaN or Inf in a numeric attribute, or values the pipeline cannot use (``check_model``:
        non-positive timestep, masses, inertias or sizes outside their sane ranges), naming the
        element or option.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"MJCF file not found: {path}")
    _check_timing(path, dt, substeps)
    spec, model, dt = _compile_checked(lambda: mujoco.MjSpec.from_file(str(path)), str(path), dt, substeps,
                                       lambda: _check_mjcf_numbers(path))
    _warn_activations(model, str(path))
    return System(name=path.stem, model=model, dt=dt, substeps=int(substeps), source=str(path), spec=spec)


def from_mjcf_string(xml: str, assets: dict | None = None, name: str = "model", dt: float | None = None,
                     substeps: int = 1, source: str = "string", translation_axes=()) -> System:
    """Loads MJCF text (with ``assets``: {file name: bytes} for its includes, meshes and textures)
    as a fixed system called ``name``; ``dt`` and ``substeps`` as ``from_mjcf``;
    ``translation_axes`` as ``System``'s. The same checks and errors as ``from_mjcf``, naming
    ``name``."""
    if not isinstance(xml, str):
        raise ValueError(f"{name}: MJCF text must be a string, got {type(xml).__name__}")
    _check_timing(name, dt, substeps)
    axes = _axes(name, translation_axes)
    spec, model, dt = _compile_checked(lambda: mujoco.MjSpec.from_string(xml, assets or {}), name, dt, substeps,
                                       lambda: _check_mjcf_text(xml, name))
    _warn_activations(model, name)
    return System(name=name, model=model, dt=dt, substeps=int(substeps), source=source, spec=spec,
                  translation_axes=axes)


def _warn_activations(model: mujoco.MjModel, name: str) -> None:
    """Warn where actuators carry a state of their own (MuJoCo's ``act``: ``dyntype`` filter,
    integrator, muscle, ...): the graphs hold body states and controls, not that state, so the
    data is not Markov in what a forward model sees."""
    if model.na == 0:
        return
    names = [_obj_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, int(i), "actuator")
             for i in np.flatnonzero(model.actuator_dyntype != mujoco.mjtDyn.mjDYN_NONE)]
    warnings.warn(f"{name}: {', '.join(names)} carr{'ies' if len(names) == 1 else 'y'} an activation state "
                  f"(MuJoCo's act, {model.na} in all, from the actuator's dyntype) that the graphs do not hold: "
                  "the data is not Markov in body states and controls, so a feed-forward model cannot predict "
                  "exactly (a recurrent model can infer it: docs/models.md)", UserWarning, stacklevel=3)


def _axes(name: str, axes) -> tuple[int, ...]:
    axes = tuple(axes)
    if any(isinstance(a, bool) or a not in (0, 1) for a in axes) or len(set(axes)) != len(axes):
        raise ValueError(f"{name}: translation_axes must hold distinct horizontal axes among 0 (x) and 1 (y), "
                         f"got {axes!r}")
    return tuple(int(a) for a in axes)


def translation_axes(name: str) -> tuple[int, ...]:
    """The translation-invariant position axes of the built-in or DMC system ``name`` (as its
    ``System.translation_axes``, without building it); () for a name that is neither."""
    from gnwarp.sim import dmc
    if dmc.is_dmc(name):
        d = dmc.DOMAINS.get(name.strip().lower())
        return d.translation_axes if d is not None else ()
    fam = family_of(name)
    return fam.translation_axes if fam is not None else ()


def _make_dmc(name: str, params, seed) -> System:
    """A DMC domain's system (``gnwarp.sim.dmc``): its own MJCF at DMC's control timestep."""
    from gnwarp.sim import dmc
    d = dmc.domain(name)
    if params is not None or seed is not None:
        raise ValueError(f"{d.name} has no parameterized variant (DMC's domains are fixed); use make({d.name!r})")
    xml, assets = dmc.model_source(d.name)
    system = from_mjcf_string(xml, assets, name=d.name, dt=d.control_dt, substeps=d.substeps, source="dm_control",
                              translation_axes=d.translation_axes)
    _fold_total_mass(system)
    return system


def _fold_total_mass(system: System) -> None:
    """Write the masses and inertias that MuJoCo's deprecated ``settotalmass`` scaling gave
    (DMC's cheetah) into the spec as explicit inertials, so that recompiling it (the MuJoCo C
    backend's sensor model) gives the same bodies without the deprecation warning."""
    spec, m = system.spec, system.model
    if spec is None or not spec.compiler.settotalmass > 0:
        return
    for i, b in enumerate(spec.bodies):
        if i == 0:
            continue
        b.mass, b.ipos, b.iquat = float(m.body_mass[i]), m.body_ipos[i].copy(), m.body_iquat[i].copy()
        b.inertia, b.explicitinertial = m.body_inertia[i].copy(), True
    spec.compiler.settotalmass = -1


# Attributes that hold names or text, never numbers (a body may be called "inf").
_TEXT_ATTRIBUTES = frozenset({
    "name", "class", "childclass", "file", "model", "prefix", "content_type", "joint", "joint1", "joint2", "jointinparent",
    "tendon", "tendon1", "tendon2", "site", "site1", "site2", "body", "body1", "body2", "bodyname", "geom", "geom1",
    "geom2", "target", "actuator", "mesh", "material", "texture", "hfield", "slidersite", "cranksite", "objname",
    "refname", "objtype", "reftype", "type", "meshdir", "texturedir", "assetdir", "key", "plugin", "instance",
    "attach", "camera", "light", "skin", "flex", "frame", "sensor", "user", "mode", "target_site", "gridlayout",
    "builtin", "mark", "fileright", "fileleft", "fileup", "filedown", "filefront", "fileback",
})


def _check_mjcf_text(xml: str, where: str) -> None:
    """``_check_mjcf_numbers`` on MJCF text (its includes come as assets, unchecked here)."""
    _check_mjcf_numbers(pathlib.Path(where), text=xml.encode("utf-8"))


def _check_mjcf_numbers(path: pathlib.Path, _seen=None, text: bytes | None = None) -> None:
    """Raise ValueError when a numeric attribute of the MJCF file (or a file it includes) holds
    NaN or Inf, naming the element, its name, the attribute and the line."""
    import xml.parsers.expat
    seen = set() if _seen is None else _seen
    path = pathlib.Path(path)
    if path.resolve() in seen or len(seen) > 100:
        return
    seen.add(path.resolve())
    found, includes = [], []
    parser = xml.parsers.expat.ParserCreate()

    def start(tag, attrs):
        if tag == "include" and "file" in attrs:
            includes.append(attrs["file"])
        for key, value in attrs.items():
            if key in _TEXT_ATTRIBUTES or found:
                continue
            tokens = value.split()
            try:
                numbers_ = [float(t) for t in tokens]
            except ValueError:
                continue
            if numbers_ and not all(math.isfinite(x) for x in numbers_):
                name = f" '{attrs['name']}'" if "name" in attrs else ""
                found.append(f"{path}: <{tag}{name}> attribute {key}=\"{value}\" (line {parser.CurrentLineNumber}) "
                             "is not finite; gnwarp needs finite numbers")

    parser.StartElementHandler = start
    try:
        parser.Parse(path.read_bytes() if text is None else text, True)
    except (xml.parsers.expat.ExpatError, OSError):
        return  # MuJoCo parsed it: nothing more to say here
    if found:
        raise ValueError(found[0])
    for inc in includes if text is None else ():
        p = path.parent / inc
        if p.is_file():
            _check_mjcf_numbers(p, seen)


def _obj_name(model: mujoco.MjModel, obj, i: int, kind: str) -> str:
    name = mujoco.mj_id2name(model, obj, i)
    return f"{kind} '{name}'" if name else f"{kind} {i} (unnamed)"


_FINITE_OPTIONS = ("gravity", "wind", "magnetic", "density", "viscosity", "impratio", "o_margin", "o_solref",
                   "o_solimp", "o_friction")
_FINITE_FIELDS = (
    ("body", mujoco.mjtObj.mjOBJ_BODY, ("body_pos", "body_quat", "body_ipos", "body_iquat")),
    ("joint", mujoco.mjtObj.mjOBJ_JOINT, ("jnt_pos", "jnt_axis", "jnt_range", "jnt_stiffness", "jnt_margin",
                                          "jnt_solref", "jnt_solimp")),
    ("dof", None, ("dof_damping", "dof_armature", "dof_frictionloss")),
    ("geom", mujoco.mjtObj.mjOBJ_GEOM, ("geom_pos", "geom_quat", "geom_friction", "geom_margin", "geom_solref",
                                        "geom_solimp")),
    ("actuator", mujoco.mjtObj.mjOBJ_ACTUATOR, ("actuator_gear", "actuator_ctrlrange", "actuator_forcerange",
                                                "actuator_gainprm", "actuator_biasprm", "actuator_dynprm")),
)

# geom type -> the size entries it uses (the others are 0): sphere radius; capsule and cylinder
# radius and half-length (which may be 0: a sphere or a disc); ellipsoid and box three half-sizes.
# Planes may have 0 (infinite); meshes, height fields and SDFs get their sizes from their data.
_GEOM_SIZES = {int(mujoco.mjtGeom.mjGEOM_SPHERE): 1, int(mujoco.mjtGeom.mjGEOM_CAPSULE): 2,
               int(mujoco.mjtGeom.mjGEOM_CYLINDER): 2, int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): 3,
               int(mujoco.mjtGeom.mjGEOM_BOX): 3}
_GEOM_USED = [[k < _GEOM_SIZES.get(t, 0) for k in range(3)] for t in range(max(_GEOM_SIZES) + 2)]  # last row: none
_HALF_LENGTH = [int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)]
_PLANE = int(mujoco.mjtGeom.mjGEOM_PLANE)


def check_model(model: mujoco.MjModel, where: str = "model") -> None:
    """Raise ValueError unless a compiled model is one the pipeline can simulate and learn.

    Checks: finite positive ``option.timestep`` and finite options; every body but the world with
    finite mass and inertia, masses in ``MASS_RANGE`` (kg) for bodies that move (welded, jointless
    bodies may be massless) and principal inertias in [0, ``INERTIA_MAX``]; primitive geoms with
    sizes in ``SIZE_RANGE`` (m; planes 0 to the upper end); finite poses, joint, dof, geom and
    actuator parameters; actuator control ranges within +-1e6. The message names ``where``, the
    option or the body / geom / joint / actuator, and the value.
    """
    def fail(msg):
        raise ValueError(f"{where}: {msg}")

    ts = float(model.opt.timestep)
    if not (math.isfinite(ts) and ts > 0):
        fail(f"option timestep is {ts!r}; it must be a finite positive number of seconds")
    opts = [np.asarray(getattr(model.opt, name), dtype=np.float64).reshape(-1) for name in _FINITE_OPTIONS]
    if not np.isfinite(np.concatenate(opts)).all():
        for name, v in zip(_FINITE_OPTIONS, opts):
            if not np.isfinite(v).all():
                fail(f"option {name} is {v.tolist()}; it must be finite")
    lo_s, hi_s = SIZE_RANGE
    size = np.asarray(model.geom_size, dtype=np.float64).reshape(-1, 3)
    gtype = np.asarray(model.geom_type).reshape(-1)
    used = np.asarray(_GEOM_USED, dtype=bool)[np.minimum(gtype, len(_GEOM_USED) - 1)]        # [ngeom, 3]
    primitive = used.any(axis=1)
    half = (gtype == _HALF_LENGTH[0]) | (gtype == _HALF_LENGTH[1])
    need = used & ~half[:, None] | (np.arange(3) == 0)[None] & primitive[:, None]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(size).all(axis=1) & (np.abs(size) <= hi_s).all(axis=1)
        ok &= np.where(primitive | (gtype == _PLANE), (size >= 0).all(axis=1), True)
        ok &= ~(need & ~(size >= lo_s)).any(axis=1)
    if not ok.all():
        g = int(np.argmin(ok))
        rng = (f"[{lo_s:g}, {hi_s:g}] m" if primitive[g] else f"[0, {hi_s:g}] m" if gtype[g] == _PLANE
               else f"within +-{hi_s:g} m")
        geom = _obj_name(model, mujoco.mjtObj.mjOBJ_GEOM, g, "geom")
        body = _obj_name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g]), "body")
        fail(f"{geom} of {body} has size {size[g].tolist()}, outside {rng}")
    lo_m, hi_m = MASS_RANGE
    mass = np.asarray(model.body_mass, dtype=np.float64)[1:]
    inertia = np.asarray(model.body_inertia, dtype=np.float64).reshape(-1, 3)[1:]
    moving = np.asarray(model.body_dofnum)[1:] > 0
    with np.errstate(invalid="ignore"):
        ok = (mass <= hi_m) & np.where(moving, mass >= lo_m, mass >= 0)  # False for NaN
    if not ok.all():
        b = int(np.argmin(ok))
        rng = f"[{lo_m:g}, {hi_m:g}] kg" if moving[b] else f"[0, {hi_m:g}] kg (a welded body may be massless)"
        fail(f"{_obj_name(model, mujoco.mjtObj.mjOBJ_BODY, b + 1, 'body')} has mass {float(mass[b])!r}, outside {rng}")
    with np.errstate(invalid="ignore"):
        ok = ((inertia >= 0) & (inertia <= INERTIA_MAX)).all(axis=1)
    if not ok.all():
        b = int(np.argmin(ok))
        fail(f"{_obj_name(model, mujoco.mjtObj.mjOBJ_BODY, b + 1, 'body')} has inertia {inertia[b].tolist()}, outside "
             f"[0, {INERTIA_MAX:g}] kg m^2 (each principal moment)")
    fields = [(kind, obj, name, np.asarray(getattr(model, name), dtype=np.float64))
              for kind, obj, names in _FINITE_FIELDS for name in names]
    if np.isfinite(np.concatenate([a.reshape(-1) for *_, a in fields])).all():
        fields = []  # all finite: nothing to name
    for kind, obj, name, a in fields:
        if a.size and not np.isfinite(a).all():
            i = int(np.argwhere(~np.isfinite(a.reshape(a.shape[0], -1)))[0][0])
            if obj is None:  # dofs: name their joint
                label = f"dof {i} of {_obj_name(model, mujoco.mjtObj.mjOBJ_JOINT, int(model.dof_jntid[i]), 'joint')}"
            else:
                label = _obj_name(model, obj, i, kind)
            fail(f"{label} has {name} {a[i].tolist()}; it must be finite")
    act = Actuators.from_model(model)
    for i in np.flatnonzero(act.limited & ((np.abs(act.low) > _CTRL_MAX) | (np.abs(act.high) > _CTRL_MAX))):
        fail(f"{_obj_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, int(i), 'actuator')} has ctrlrange "
             f"{[float(act.low[i]), float(act.high[i])]}, beyond +-{_CTRL_MAX:g}")


def _actuator_type(model: mujoco.MjModel, i: int) -> str:
    """motor, velocity, position or general, by the gain and bias of actuator i."""
    gain, bias = model.actuator_gaintype[i], model.actuator_biastype[i]
    dyn = model.actuator_dyntype[i]
    fixed = mujoco.mjtGain.mjGAIN_FIXED
    if dyn != mujoco.mjtDyn.mjDYN_NONE or gain != fixed:
        return "general"
    if bias == mujoco.mjtBias.mjBIAS_NONE:
        return "motor"
    if bias == mujoco.mjtBias.mjBIAS_AFFINE:
        kp, kv = -model.actuator_biasprm[i, 1], -model.actuator_biasprm[i, 2]
        g = model.actuator_gainprm[i, 0]
        if kp == 0 and kv > 0 and math.isclose(g, kv):
            return "velocity"
        if kp > 0 and math.isclose(g, kp):
            return "position"
    return "general"


def describe(system: System) -> dict:
    """One row of `gnwarp systems`: sizes, actuator types, timesteps and parameter ranges.

    "parameters" gives the ranges of the system's parameterized variant (per-body and per-link
    factors collapsed into one entry each, e.g. "link_length_*"); {} where there is none.
    """
    model = system.model
    types: list[str] = []
    for i in range(model.nu):
        kind = _actuator_type(model, i)
        if kind not in types:
            types.append(kind)
    parameters: dict[str, tuple[float, float]] = {}
    if system.source == "builtin":
        fam, _ = parse_name(system.name)
        for _, label, rng in fam.ranges():
            parameters.setdefault(label, rng)
    return {
        "name": system.name,
        "bodies": system.nbody,
        "nq": system.nq,
        "nv": system.nv,
        "nu": system.nu,
        "actuators": ", ".join(types),
        "timestep": system.timestep,
        "dt": system.dt,
        "substeps": system.substeps,
        "contacts": system.contacts,
        "parameters": parameters,
    }
